"""drivectl health run: the fingerprint profile on a session (the resident loop), its trace with
# machine: and # started_utc:, ingested; refusals in one line before anything moves (soft limits, an
axis not enabled); a run a fault ends is kept on disk and not ingested; [axes.NAME.health] and
[health.limits] in the configuration."""

from __future__ import annotations

import re
from pathlib import Path

import pytest

pytest.importorskip("duckdb")
pytest.importorskip("pyarrow")

import drivectl  # noqa: E402
from drivectl.driver.axis import AxisError  # noqa: E402
from drivectl.machine.config import ConfigError, load_config  # noqa: E402
from drivectl.profiles.library import load_profile  # noqa: E402
from drivectl.tools.cli.main import main  # noqa: E402
from drivectl.tools.health.fingerprint import run_fingerprint  # noqa: E402
from drivectl.tools.health.store import Store  # noqa: E402
from drivectl.tracefile.format import Trace  # noqa: E402

SHORT = Path(__file__).with_name("data") / "health-short.toml"


def _config(tmp_path: Path, extra: str = "", position: str = "[-0.1, 0.1]") -> Path:
    cfg = tmp_path / "quench-3.toml"
    cfg.write_text(f'[axes.x]\nplant = "rigid-x"\ncontroller = "mbc"\nprofile = "short-move"\n'
                   f"[axes.x.limits]\nposition_m = {position}\n{extra}")
    return cfg


def test_the_fingerprint_is_about_ten_seconds_of_reversals_passes_and_a_dwell():
    import numpy as np

    p = load_profile("fingerprint")
    assert 8.0 <= p.duration <= 12.0
    t = np.arange(0, p.duration, 1e-3)
    pos, vel = p.sample(t)[:2]
    moving = np.abs(vel) > 1e-6
    edges = np.flatnonzero(np.diff(moving.astype(int)))  # the moves between standstills
    moves = [(a + 1, b + 1) for a, b in zip(edges[::2], edges[1::2], strict=False)]
    peaks = [float(np.max(np.abs(vel[a:b]))) for a, b in moves]
    signs = [float(np.sign(vel[(a + b) // 2])) for a, b in moves]
    assert len(moves) >= 8 and sum(s1 != s2 for s1, s2 in zip(signs, signs[1:], strict=False)) >= 7  # reversals
    assert len({round(v, 3) for v in peaks[:6]}) == 3  # out and back at three speeds
    slow = [(b - a) * 1e-3 for (a, b), v in zip(moves, peaks, strict=True) if v <= 0.03]
    assert sum(slow) >= 4.0 and np.ptp(pos) >= 0.05 - 1e-9  # slow passes over 50 mm
    assert not moving[-900:].any()  # the dwell at the end


def test_health_run_writes_the_trace_with_machine_and_start_and_ingests_it(tmp_path, capsys):
    cfg = _config(tmp_path, f'[axes.x.health]\nprofile = "{SHORT.name}"\n')
    (tmp_path / SHORT.name).write_text(SHORT.read_text())  # relative to the configuration's folder
    store, out = tmp_path / "store", tmp_path / "traces"
    assert main(["--config", str(cfg), "health", "run", "--axis", "x", "--sim", "--store", str(store),
                 "--out", str(out)]) == 0
    line = capsys.readouterr().out.strip().splitlines()[-1]
    assert re.fullmatch(r"health run x: done; trace .*x-\d{8}T\d{6}Z\.csv \(ingested\)", line), line
    (trace_path,) = out.glob("x-*.csv")
    tr = Trace.read(trace_path)
    assert tr.meta["machine"] == "quench-3"  # the configuration file's stem
    assert re.fullmatch(r"\d{4}-\d\d-\d\dT\d\d:\d\d:\d\dZ", tr.meta["started_utc"])
    assert tr.meta["profile"] == "health-short" and tr.meta["stop"] == "done"
    with Store(store) as s:
        (run,) = s.runs()
    assert (run["machine"], run["axis"], run["started_from"], run["samples"]) == ("quench-3", "x", "header", len(tr))


def test_health_run_refuses_a_fingerprint_past_the_soft_limits_before_anything_moves(tmp_path, capsys):
    cfg = _config(tmp_path, position="[-0.1, 0.03]")
    store, out = tmp_path / "store", tmp_path / "traces"
    assert main(["--config", str(cfg), "health", "run", "--axis", "x", "--sim", "--store", str(store),
                 "--out", str(out)]) == 2
    err = capsys.readouterr().err.strip().splitlines()
    assert len(err) == 1 and "health run fingerprint: position 0.03" in err[0]
    assert "axes.x.limits.position_m" in err[0] and err[0].endswith("nothing moved")
    assert not store.exists() and not list(out.glob("*.csv"))


def test_run_fingerprint_refuses_an_axis_that_is_not_enabled(tmp_path):
    with drivectl.connect(axes=["x"], sim=True, fault_dir=None) as m:
        before = m.axes["x"].position
        with pytest.raises(AxisError, match=r"^axis x: health run: not enabled \(enable it first\); nothing moved$"):
            run_fingerprint(m, "x", machine_name="m1", out=tmp_path / "traces", store=tmp_path / "store")
        assert m.axes["x"].position == before
    assert not (tmp_path / "traces").exists() and not (tmp_path / "store").exists()


def test_a_run_a_fault_ends_is_kept_on_disk_and_not_ingested(tmp_path):
    profile = load_profile(SHORT)
    with drivectl.connect(axes=["x"], faults=["emcy-fault@1.0"], fault_dir=None) as m:
        m.axes["x"].enable()
        r = run_fingerprint(m, "x", machine_name="m1", out=tmp_path / "traces", store=tmp_path / "store",
                            profile=profile)
    assert r.status == "fault" and r.ingest is None and "not ingested" in r.line
    assert Trace.read(r.trace).meta["stop"] == "fault"
    assert not (tmp_path / "store").exists()


def test_health_configuration_keys(tmp_path):
    cfg = load_config(_config(tmp_path, '[health.limits]\nbacklash.width = "15um"\ncoulomb.force_pos = 60\n'
                                        '[axes.x.health.limits]\nviscous.scale = 1.3\ndelay.delay = "3ms"\n'))
    lim = cfg.health_limits_of("x")
    assert lim["backlash.width"] == pytest.approx(15e-6) and lim["coulomb.force_pos"] == 60.0
    assert lim["viscous.scale"] == 1.3 and lim["delay.delay"] == pytest.approx(3e-3)
    assert load_config().health_limits_of("x")["backlash.width"] == pytest.approx(20e-6)  # the default
    assert cfg.axes["x"].health.profile == "fingerprint"
    bad = {
        '[axes.x.health]\nprofile = 3\n': "axes.x.health.profile: expected a profile name",
        '[axes.x.health]\nprofile = "nope"\n': "axes.x.health.profile: profile 'nope': no such library profile",
        '[axes.x.health]\nprofil = "fingerprint"\n': "axes.x.health.profil: unknown key",
        '[health.limits]\nbacklash.width = "20 parsecs"\n': "health.limits.backlash.width: unit 'parsecs'",
        '[health.limits]\nwear.width = 1\n': "health.limits.wear: unknown effect",
        '[axes.x.health.limits]\nbacklash.depth = 1\n': "axes.x.health.limits.backlash.depth: not a parameter",
        '[health.limits]\nviscous.scale = "lots"\n': "health.limits.viscous.scale: expected a number in 1",
    }
    for extra, want in bad.items():
        path = _config(tmp_path, extra)
        with pytest.raises(ConfigError) as exc:
            load_config(path)
        msg = str(exc.value)
        assert len(msg.splitlines()) == 1 and str(path) in msg and want in msg, msg
