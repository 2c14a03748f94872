"""Issue 7 point 7: bad input of every kind gets one line naming the file (or node) and the field,
exit code 2, and nothing half-written. Each case differs from a valid input in one place; the valid
inputs are run too, so a case fails for the reason it claims."""

from __future__ import annotations

import re
from pathlib import Path

import pytest

from drivectl.tools.cli import main
from drivectl.tools.config import DEFAULT_CONFIG_TOML as BASE

EDS = Path(__file__).resolve().parent.parent / "driver" / "eds" / "drivectl-emulated-drive.eds"
PTP = 'kind = "ptp"\nstart = 0.0\ntarget = 0.01\nvmax = 0.05\namax = 0.5\njmax = 20.0\nhold_until = 0.5\n'
PLANT = (Path(__file__).resolve().parent.parent / "plant_emulator" / "plants" / "rigid-x.toml").read_text()
TRACE = ("# drivectl trace v1\n# axis: x\n# dt_s: 0.001\ntime_s,ref_m,pos_m,effort\n"
         "0.000,0.0,0.0,0.0\n0.001,0.0,0.0,1.0\n0.002,0.0,0.0,2.0\n")


def _edit(text: str, old: str, new: str) -> str:
    assert old in text, old
    return text.replace(old, new, 1)


def _eds_without(index: str) -> str:
    """The emulated drive's EDS with one object removed (section and object list entry)."""
    text = EDS.read_text()
    text = re.sub(rf"\r?\n\[{index}(sub[0-9A-Fa-f]+)?\]\r?\n(?:[^\[\r\n].*\r?\n)*", "\n", text)
    return re.sub(rf"(?m)^\d+=0x{index}\r?\n", "", text)


def _eds_vendor(value: str) -> str:
    """The EDS of another maker's drive: the master expects that vendor in 0x1018."""
    return re.sub(r"(?m)^VendorNumber=[^\r\n]+", f"VendorNumber={value}", EDS.read_text())


TRACE_ARGS = ["trace", "--axis", "x", "--duration", "0.05", "--no-plot", "--quiet"]

# (id, kind of file, its text (None: no file), argv after the file option, substrings the line must hold)
CASES = [
    # machine configuration
    ("config-wrong-type", "config", _edit(BASE, "cycle_s = 0.001", 'cycle_s = "fast"'), TRACE_ARGS, ("cycle_s",)),
    ("config-negative-cycle", "config", _edit(BASE, "cycle_s = 0.001", "cycle_s = -0.001"), TRACE_ARGS, ("cycle_s",)),
    ("config-toml-syntax", "config", _edit(BASE, "[axes.x]\n", "[axes.x\n"), TRACE_ARGS, ("not valid TOML",)),
    ("config-missing-plant", "config", _edit(BASE, 'plant = "rigid-x"               # built-in plant name or a plant '
                                             'TOML file\n', ""), TRACE_ARGS, ("axes.x.plant", "missing")),
    ("config-unknown-key", "config", _edit(BASE, "max_lost_cycles = 3 ", "speed = 3\nmax_lost_cycles = 3 "),
     TRACE_ARGS, ("axes.x.speed", "unknown key")),
    ("config-node-id-zero", "config", _edit(BASE, "node_id = 1\n", "node_id = 0\n"), TRACE_ARGS, ("axes.x.node_id",)),
    ("config-node-id-type", "config", _edit(BASE, "node_id = 1\n", 'node_id = "one"\n'), TRACE_ARGS,
     ("axes.x.node_id",)),
    ("config-node-id-shared", "config", _edit(BASE, "node_id = 2\n", "node_id = 1\n"), TRACE_ARGS,
     ("axes", "share a node_id")),
    ("config-rated-negative", "config", _edit(BASE, "rated_effort = 100.0         # N per 1000 per mille of 0x6071 "
                                              "(0x6076); 0.1 % = 0.1 N\nplant", "rated_effort = -1.0\nplant"),
     TRACE_ARGS, ("axes.x.rated_effort",)),
    ("config-encoder-type", "config", _edit(BASE, "encoder_m_per_count = 76.29e-9\nmax_lost",
                                            "encoder_m_per_count = [1]\nmax_lost"), TRACE_ARGS,
     ("axes.x.encoder_m_per_count",)),
    ("config-limits-inverted", "config", _edit(BASE, "position_m = [-0.1, 0.1]        # soft limits",
                                               "position_m = [0.1, -0.1]"), TRACE_ARGS,
     ("axes.x.limits.position_m", "below")),
    ("config-limits-shape", "config", _edit(BASE, "position_m = [-0.1, 0.1]        # soft limits", "position_m = 0.1"),
     TRACE_ARGS, ("axes.x.limits.position_m",)),
    ("config-max-effort-negative", "config", _edit(BASE, "max_effort = 2000.0             # N, the command is "
                                                   "clipped here", "max_effort = -5.0"), TRACE_ARGS,
     ("axes.x.limits.max_effort",)),
    ("config-following-zero", "config", _edit(BASE, "following_error_m = 0.001       # window",
                                              "following_error_m = 0.0"), TRACE_ARGS,
     ("axes.x.limits.following_error_m",)),
    ("config-max-speed-negative", "config", _edit(BASE, "max_speed_m_s = 2.0 ", "max_speed_m_s = -2.0 "), TRACE_ARGS,
     ("axes.x.limits.max_speed_m_s",)),
    ("config-max-lost-negative", "config", _edit(BASE, "max_lost_cycles = 3 ", "max_lost_cycles = -1 "), TRACE_ARGS,
     ("axes.x.max_lost_cycles",)),
    ("config-rpdo-timeout-type", "config", _edit(BASE, "rpdo_timeout_ms = 2 ", 'rpdo_timeout_ms = "2" '),
     TRACE_ARGS, ("axes.x.rpdo_timeout_ms",)),
    ("config-negative-gain", "config", _edit(BASE, "law = 14                        # paper 004 gain law (11..14)",
                                             "law = 14\ngamma = -50.0"), TRACE_ARGS,
     ("axes.x.controller_settings", "gamma")),
    ("config-beta-out-of-range", "config",
     _edit(BASE, "accel_filter_hz = 150.0", "accel_filter_hz = 150.0\nbeta = 1.5"),
     ["trace", "--axis", "z", "--duration", "0.05", "--no-plot", "--quiet"], ("axes.z.controller_settings", "beta")),
    ("config-law-out-of-range", "config", _edit(BASE, "law = 14                        # paper 004 gain law (11..14)",
                                                "law = 15"), TRACE_ARGS, ("axes.x.controller_settings", "law")),
    ("config-unknown-setting", "config", _edit(BASE, "law = 14                        # paper 004 gain law (11..14)",
                                               "law = 14\nzeta = 1.0"), TRACE_ARGS,
     ("axes.x.controller_settings", "zeta")),
    ("config-unknown-controller", "config", _edit(BASE, 'controller = "asmc"             # smc',
                                                  'controller = "lqr"             # smc'), TRACE_ARGS,
     ("axes.x.controller", "lqr")),
    ("config-unknown-interface", "config", _edit(BASE, 'interface = "virtual"', 'interface = "can4linux"'),
     TRACE_ARGS, ("bus.interface",)),
    # profiles
    ("profile-wrong-type", "profile", _edit(PTP, "vmax = 0.05", 'vmax = "fast"'), TRACE_ARGS, ("vmax",)),
    ("profile-missing-key", "profile", _edit(PTP, "target = 0.01\n", ""), TRACE_ARGS, ("target", "missing")),
    ("profile-negative-speed", "profile", _edit(PTP, "vmax = 0.05", "vmax = -0.05"), TRACE_ARGS, ("vmax",)),
    ("profile-unknown-kind", "profile", _edit(PTP, 'kind = "ptp"', 'kind = "spline"'), TRACE_ARGS, ("kind",)),
    ("profile-toml-syntax", "profile", PTP + "[oops\n", TRACE_ARGS, ("TOML",)),
    ("profile-outside-soft-limits", "profile", _edit(PTP, "target = 0.01", "target = 0.5"),
     ["trace", "--axis", "x", "--no-plot", "--quiet"], ("soft limits", "nothing moved")),
    # plants
    ("plant-wrong-type", "plant", _edit(PLANT, "mass = 88.08", 'mass = "heavy"'), TRACE_ARGS, ("params.mass",)),
    ("plant-negative-mass", "plant", _edit(PLANT, "mass = 88.08", "mass = -88.08"), TRACE_ARGS, ("params.mass",)),
    ("plant-missing-params", "plant", PLANT.split("[params]")[0], TRACE_ARGS, ("params",)),
    ("plant-unknown-model", "plant", _edit(PLANT, 'model = "rigid"', 'model = "flexible"'), TRACE_ARGS, ("model",)),
    # traces (read by summary and by plot)
    ("trace-truncated", "trace", TRACE[:-8], ["summary"], ("garbled",)),
    ("trace-garbled-number", "trace", _edit(TRACE, "0.001,0.0,0.0,1.0", "0.001,0.0,abc,1.0"), ["plot"], ("garbled",)),
    ("trace-missing-column", "trace", TRACE.replace("time_s,ref_m,pos_m,effort", "time_s,ref_m,effort"),
     ["summary"], ("pos_m",)),
    ("trace-time-not-increasing", "trace", _edit(TRACE, "0.002,", "0.001,"), ["plot"], ("time_s", "row 3")),
    ("trace-nan", "trace", _edit(TRACE, "0.001,0.0,0.0,1.0", "0.001,0.0,nan,1.0"), ["summary"], ("pos_m", "row 2")),
    ("trace-empty", "trace", "", ["summary"], ("column row",)),
    ("trace-header-only", "trace", "time_s,ref_m,pos_m,effort\n", ["plot"], ("no data rows",)),
    # the drive and its description
    ("eds-missing-object", "eds", _eds_without("6077"), TRACE_ARGS, ("axis x", "bad-eds.eds", "0x6077")),
    ("eds-of-another-drive", "eds", _eds_vendor("0x12345678"), TRACE_ARGS,
     ("node 1", "identity", "expects vendor 0x12345678")),
    ("sdo-abort-while-configuring", None, None, [*TRACE_ARGS, "--fault", "sdo-abort:index=0x6060"],
     ("node 1", "SDO 0x6060 aborted")),
    ("fault-spec", None, None, [*TRACE_ARGS, "--fault", "tpdo-lost:cycles=0@1"], ("--fault", "cycles")),
]


def _prepare(tmp_path: Path, kind: str | None, text: str | None, argv: list[str]) -> tuple[list[str], str | None]:
    """The full argv for a case and the file name the error must name."""
    out = ["--out", str(tmp_path / "out")]
    if kind is None:
        return [*argv, *out], None
    suffix = {"trace": ".csv", "eds": ".eds"}.get(kind, ".toml")
    path = tmp_path / f"bad-{kind}{suffix}"
    path.write_text(text)
    if kind == "config":
        return ["--config", str(path), *argv, *out], str(path)
    if kind == "profile":
        return [*argv, "--profile", str(path), *out], path.stem
    if kind == "plant":
        return [*argv, "--plant", str(path), *out], str(path)
    if kind == "trace":
        extra = ["--out", str(tmp_path / "out" / "plot.png")] if argv == ["plot"] else []
        return [argv[0], str(path), *extra], str(path)
    cfg = tmp_path / "machine.toml"
    cfg.write_text(_edit(BASE, "[axes.x]\n", f'[axes.x]\neds = "{path}"\n'))
    return ["--config", str(cfg), *argv, *out], None  # the drive's refusal names the node (and the EDS)


def test_the_matrix_is_big_enough():
    assert len(CASES) >= 30 and len({c[0] for c in CASES}) == len(CASES)


@pytest.mark.parametrize(("kind", "text", "argv", "fragments"), [c[1:] for c in CASES], ids=[c[0] for c in CASES])
def test_bad_input_one_line_exit_2_nothing_written(tmp_path, capsys, kind, text, argv, fragments):
    full, named = _prepare(tmp_path, kind, text, argv)
    before = {p: p.read_bytes() for p in tmp_path.rglob("*") if p.is_file()}
    rc = main(full)
    err = capsys.readouterr().err
    lines = err.strip().splitlines()
    assert rc == 2, err
    assert len(lines) == 1 and lines[0].startswith("drivectl: ") and "Traceback" not in err, err
    line = lines[0]
    if named is not None:
        assert named in line, line
    for fragment in fragments:
        assert fragment in line, line
    out = tmp_path / "out"
    assert not out.exists() or not any(out.iterdir()), list(out.iterdir())
    after = {p: p.read_bytes() for p in tmp_path.rglob("*") if p.is_file()}
    assert after == before  # no input touched, no temporary left behind


@pytest.mark.parametrize("base", ["config", "profile", "plant", "trace"])
def test_the_valid_inputs_run(tmp_path, capsys, base):
    """The unedited inputs pass, so every case above fails for its own edit."""
    text = {"config": BASE, "profile": PTP, "plant": PLANT, "trace": TRACE}[base]
    argv = ["summary"] if base == "trace" else TRACE_ARGS
    full, _ = _prepare(tmp_path, base, text, argv)
    assert main(full) == 0, capsys.readouterr().err


def test_valid_eds_copy_runs(tmp_path, capsys):
    full, _ = _prepare(tmp_path, "eds", EDS.read_text(), TRACE_ARGS)
    assert main(full) == 0, capsys.readouterr().err


def test_config_init_never_overwrites(tmp_path, capsys):
    path = tmp_path / "machine.toml"
    path.write_text("# mine\n")
    assert main(["config", "init", str(path)]) == 2
    err = capsys.readouterr().err.strip().splitlines()
    assert len(err) == 1 and str(path) in err[0] and "exists" in err[0]
    assert path.read_text() == "# mine\n" and [p.name for p in tmp_path.iterdir()] == ["machine.toml"]
