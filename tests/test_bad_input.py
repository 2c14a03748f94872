"""Issue 7 point 7, the bad-input matrix: configuration, profile, plant, trace and EDS files with a wrong
type, a missing key, an out-of-range value, a truncated or garbled CSV, an EDS without an essential object,
an SDO abort from the drive while it is configured, and ``config init`` over an existing file.

Every case runs the real CLI entry point in-process and must give exit code 2, exactly one line on stderr
("drivectl: ...", no traceback) naming the file (or the node) and the field, and leave nothing written:
the --out folder absent or empty, no ``*.tmp`` anywhere, every file that was there before unchanged.

Each case differs from a valid input in one place (string edits of the embedded default configuration,
of the short-move profile, of the rigid-x plant, of a small trace, of the emulated drive's EDS); the
valid inputs are run too (``test_the_valid_bases_run``), so a case fails for the reason it claims.

Expected fragments may hold ``{path}`` (the bad file's full path) and ``{name}`` (its basename).
"""

from __future__ import annotations

import re
from pathlib import Path

import pytest

from drivectl.machine.config import DEFAULT_CONFIG_TOML as CONFIG
from drivectl.tools.cli.main import main

ROOT = Path(__file__).resolve().parent.parent
EDS = (ROOT / "driver" / "eds" / "drivectl-emulated-drive.eds").read_text()
PLANT = (ROOT / "plant_emulator" / "plants" / "rigid-x.toml").read_text()
PROFILE = (ROOT / "profiles" / "library" / "short-move.toml").read_text()
DWELL = 'kind = "dwell"\nposition = 0.0\nduration = 0.5\n'
TRACE = (
    "# drivectl trace v1\n# axis: x\n# effort_unit: N\n# dt_s: 0.001\n"
    "time_s,ref_m,pos_m,effort\n"
    "0.000000,0.000000000,0.000000000,0.000000\n"
    "0.001000,0.000001000,0.000000500,10.000000\n"
    "0.002000,0.000002000,0.000001500,20.000000\n"
    "0.003000,0.000003000,0.000002500,30.000000\n"
)

SIM = ["trace", "--axis", "x", "--duration", "0.05", "--no-plot", "--quiet", "--sim"]
SIM_Z = ["trace", "--axis", "z", "--duration", "0.05", "--no-plot", "--quiet", "--sim"]
BUS = ["trace", "--axis", "x", "--duration", "0.05", "--no-plot", "--quiet"]  # emulated drive, virtual bus
SIM_FULL = ["trace", "--axis", "x", "--no-plot", "--quiet", "--sim"]  # the profile's whole duration


def edit(text: str, old: str, new: str) -> str:
    """``text`` with its one occurrence of ``old`` replaced (the edit must hit exactly one place)."""
    assert text.count(old) == 1, f"{old!r} occurs {text.count(old)} times"
    return text.replace(old, new)


def line_of(text: str, line: str) -> int:
    return text.splitlines().index(line) + 1


#: x under paper 004's ASMC with law 14 (the embedded comment's recipe): its settings' checks are exercised there
X_MBC = 'controller = "mbc"              # mbc'
CONFIG_ASMC = edit(edit(CONFIG, X_MBC, 'controller = "asmc"             # mbc'),
                   "# law = 14                      # paper 004", "law = 14                        # paper 004")


def eds_without(index: str) -> str:
    """The emulated drive's EDS without object ``index``: its section and sub-sections gone, and the object
    lists renumbered with their counts lowered, so that the file stays well-formed."""
    text = re.sub(rf"(?ms)^\[{index}(sub[0-9A-Fa-f]+)?\]\n.*?(?=^\[|\Z)", "", EDS)

    def renumber(m: re.Match) -> str:
        values = [v for v in re.findall(r"(?m)^\d+=(\S+)$", m.group(2)) if v.upper() != f"0X{index}"]
        return (m.group(1) + f"SupportedObjects={len(values)}\n"
                + "".join(f"{i}={v}\n" for i, v in enumerate(values, 1)) + "\n")

    text = re.sub(r"(?ms)^(\[(?:Mandatory|Optional|Manufacturer)Objects\]\n)(.*?)(?=^\[|\Z)", renumber, text)
    assert f"[{index}]" not in text and not re.search(rf"(?m)^\d+=0x{index}$", text)
    return text


def without_column(trace: str, j: int) -> str:
    """``trace`` with its column ``j`` (header and every row) taken out."""
    lines = [ln if ln.startswith("#") else ",".join(c for i, c in enumerate(ln.split(",")) if i != j)
             for ln in trace.splitlines()]
    return "\n".join(lines) + "\n"


def config_with_eds(eds_path: Path) -> str:
    return edit(CONFIG, "[axes.x]\nnode_id = 1\n", f'[axes.x]\nnode_id = 1\neds = "{eds_path}"\n')


# (id, kind of the bad file, its text, argv (the file option and --out are added), expected fragments)
# kinds: config (--config FILE), profile (--profile FILE), plant (--plant FILE), trace (summary/plot FILE),
# eds (a config whose axis x reads the bad EDS), args (no file: the command line), init (config init FILE over an
# existing FILE).
CASES = [
    # -- machine configuration ---------------------------------------------------------------------------
    ("config-toml-syntax", "config", edit(CONFIG, "[axes.x]\n", "[axes.x\n"), SIM,
     ("{path}", "not valid TOML", f"line {line_of(CONFIG, '[axes.x]')}")),
    ("config-unknown-top-key", "config", edit(CONFIG, "cycle_s = 0.001", "cycle_ms = 1"), SIM,
     ("{path}", "cycle_ms", "unknown key")),
    ("config-cycle-wrong-type", "config", edit(CONFIG, "cycle_s = 0.001", 'cycle_s = "fast"'), SIM,
     ("{path}", "cycle_s", "'fast'")),
    ("config-cycle-negative", "config", edit(CONFIG, "cycle_s = 0.001", "cycle_s = -0.001"), SIM,
     ("{path}", "cycle_s", "-0.001")),
    ("config-axes-missing", "config", CONFIG[: CONFIG.index("[axes.x]\n")], SIM, ("{path}", "axes:")),
    ("config-axis-missing-plant", "config", edit(CONFIG, 'plant = "rigid-x"', "# plant"), SIM,
     ("{path}", "axes.x.plant", "missing")),
    ("config-axis-missing-controller", "config", edit(CONFIG, X_MBC, "# mbc"), SIM,
     ("{path}", "axes.x.controller", "missing")),
    ("config-axis-missing-profile", "config", edit(CONFIG, 'profile = "circle"              #', "#"), SIM,
     ("{path}", "axes.x.profile", "missing")),
    ("config-axis-unknown-key", "config", edit(CONFIG, "max_lost_cycles = 3 ", "max_lost_cycle = 3 "), SIM,
     ("{path}", "axes.x.max_lost_cycle", "unknown key")),
    ("config-limits-inverted", "config", edit(CONFIG, "position_m = [-0.1, 0.1]   ", "position_m = [0.1, -0.1]   "),
     SIM, ("{path}", "axes.x.limits.position_m")),
    ("config-limits-wrong-length", "config",
     edit(CONFIG, "position_m = [-0.1, 0.1]   ", "position_m = [-0.1, 0.0, 0.1]   "), SIM,
     ("{path}", "axes.x.limits.position_m", "[lower, upper]")),
    ("config-max-effort-negative", "config", edit(CONFIG, "max_effort = 300.0 ", "max_effort = -300.0 "), SIM,
     ("{path}", "axes.x.limits.max_effort", "-300")),
    ("config-following-error-zero", "config", edit(CONFIG, "following_error_m = 0.001       #",
                                                   "following_error_m = 0.0       #"), SIM,
     ("{path}", "axes.x.limits.following_error_m")),
    ("config-following-time-negative", "config", edit(CONFIG, "following_time_s = 0.01\nmax_speed",
                                                      "following_time_s = -0.01\nmax_speed"), SIM,
     ("{path}", "axes.x.limits.following_time_s", "-0.01")),
    ("config-node-id-zero", "config", edit(CONFIG, "node_id = 1\n", "node_id = 0\n"), SIM,
     ("{path}", "axes.x.node_id", "got 0")),
    ("config-node-id-200", "config", edit(CONFIG, "node_id = 1\n", "node_id = 200\n"), SIM,
     ("{path}", "axes.x.node_id", "200")),
    ("config-node-id-string", "config", edit(CONFIG, "node_id = 1\n", 'node_id = "one"\n'), SIM,
     ("{path}", "axes.x.node_id", "'one'")),
    ("config-node-id-shared", "config", edit(CONFIG, "node_id = 2\n", "node_id = 1\n"), SIM,
     ("{path}", "axes.y.node_id", "axes.x.node_id")),
    ("config-rated-effort-too-large", "config", edit(CONFIG, "rated_effort = 100.0         # N per 1000 per mille "
                                                     "of 0x6071 (0x6076); 0.1 % = 0.1 N\nplant = \"rigid-x\"",
                                                     'rated_effort = 1e7\nplant = "rigid-x"'), BUS,
     ("{path}", "axes.x.rated_effort", "0x6076")),
    ("config-encoder-overflows-counts", "config", edit(CONFIG, "encoder_m_per_count = 76.29e-9\nmax_lost",
                                                       "encoder_m_per_count = 1e-15\nmax_lost"), BUS,
     ("{path}", "axes.x.encoder_m_per_count", "0x6064")),
    ("config-rated-effort-negative", "config", edit(CONFIG, "rated_effort = 100.0         # N per 1000 per mille "
                                                    "of 0x6071 (0x6076); 0.1 % = 0.1 N\nplant = \"rigid-x\"",
                                                    'rated_effort = -100.0\nplant = "rigid-x"'), SIM,
     ("{path}", "axes.x.rated_effort", "-100")),
    ("config-encoder-wrong-type", "config", edit(CONFIG, "encoder_m_per_count = 76.29e-9\nmax_lost",
                                                 'encoder_m_per_count = "fine"\nmax_lost'), SIM,
     ("{path}", "axes.x.encoder_m_per_count", "'fine'")),
    ("config-controller-negative-gain", "config", edit(CONFIG_ASMC, "law = 14                        #",
                                                       "gamma = -50.0\nlaw = 14 #"), SIM,
     ("{path}", "axes.x.controller_settings", "gamma", "-50")),
    ("config-controller-gain-wrong-type", "config", edit(CONFIG_ASMC, "law = 14                        #",
                                                         'k_bar = "high"\nlaw = 14 #'), SIM,
     ("{path}", "axes.x.controller_settings", "k_bar", "'high'")),
    ("config-controller-gain-array", "config", edit(CONFIG_ASMC, "law = 14                        #",
                                                    "gamma = [50.0, 60.0]\nlaw = 14 #"), SIM,
     ("{path}", "axes.x.controller_settings", "gamma", "[50.0, 60.0]")),
    ("config-nftsm-beta-out-of-range", "config", edit(edit(CONFIG, "# accel_filter_hz = 150.0\n",
                                                           "accel_filter_hz = 150.0\nbeta = 1.2\n"),
                                                      'controller = "mbc"              # paper 000',
                                                      'controller = "pid-nftsm"        # paper 000'), SIM_Z,
     ("{path}", "axes.z.controller_settings", "beta", "(0.5, 1)", "1.2")),
    ("config-controller-law-not-a-choice", "config", edit(CONFIG_ASMC, "law = 14                        #",
                                                          "law = 15 #"), SIM,
     ("{path}", "axes.x.controller_settings", "law", "15")),
    ("config-unknown-controller-setting", "config", edit(CONFIG_ASMC, "law = 14                        #",
                                                         "zeta = 0.7\nlaw = 14 #"), SIM,
     ("{path}", "axes.x.controller_settings", "zeta", "unknown setting")),
    ("config-unknown-controller", "config", edit(CONFIG, X_MBC, 'controller = "lqr"              # mbc'), SIM,
     ("{path}", "axes.x.controller", "'lqr'")),
    ("config-limits-not-a-pair", "config", edit(CONFIG, "position_m = [-0.1, 0.1]   ", "position_m = 0.1   "), SIM,
     ("{path}", "axes.x.limits.position_m", "[lower, upper]", "0.1")),
    ("config-max-speed-negative", "config", edit(CONFIG, "max_speed_m_s = 2.0 ", "max_speed_m_s = -2.0 "), SIM,
     ("{path}", "axes.x.limits.max_speed_m_s", "-2.0")),
    ("config-max-lost-cycles-negative", "config", edit(CONFIG, "max_lost_cycles = 3 ", "max_lost_cycles = -1 "),
     BUS, ("{path}", "axes.x.max_lost_cycles", "-1")),
    ("config-rpdo-timeout-string", "config", edit(CONFIG, "# rpdo_timeout_ms = 6 ", 'rpdo_timeout_ms = "2" '), BUS,
     ("{path}", "axes.x.rpdo_timeout_ms", "'2'")),
    ("config-plant-file-missing", "config", edit(CONFIG, 'plant = "rigid-x"', 'plant = "no-such-plant.toml"'), SIM,
     ("{path}", "axes.x.plant", "no-such-plant.toml", "no such plant file")),
    ("config-profile-unknown", "config", edit(CONFIG, '[axes.x]\nnode_id = 1\n',
                                              '[axes.x]\nnode_id = 1\nprofile = "spiral"\n').replace(
        'profile = "circle"              #', "#", 1), SIM, ("{path}", "axes.x.profile", "'spiral'")),
    ("config-bus-interface-unknown", "config", edit(CONFIG, 'interface = "virtual"', 'interface = "can4linux"'),
     BUS, ("{path}", "bus.interface", "'can4linux'")),
    ("config-bus-bitrate-negative", "config", edit(CONFIG, "bitrate = 1000000", "bitrate = -1000000"), BUS,
     ("{path}", "bus.bitrate", "-1000000")),
    # -- profiles (--profile FILE) -----------------------------------------------------------------------
    ("profile-toml-syntax", "profile", edit(PROFILE, "vmax = 0.05", "vmax = 0.05 0.06"), SIM,
     ("{path}", "invalid TOML", "vmax")),
    ("profile-wrong-type", "profile", edit(PROFILE, "vmax = 0.05", 'vmax = "fast"'), SIM,
     ("{path}", "vmax", "'fast'")),
    ("profile-missing-key", "profile", edit(PROFILE, "target = 0.01\n", ""), SIM, ("{path}", "target", "missing")),
    ("profile-negative-velocity-limit", "profile", edit(PROFILE, "vmax = 0.05", "vmax = -0.05"), SIM,
     ("{path}", "vmax", "-0.05")),
    ("profile-negative-duration", "profile", edit(DWELL, "duration = 0.5", "duration = -1.0"), SIM,
     ("{path}", "duration", "-1.0")),
    ("profile-unknown-kind", "profile", edit(PROFILE, 'kind = "ptp"', 'kind = "spline"'), SIM,
     ("{path}", "kind", "'spline'")),
    ("profile-unknown-key", "profile", edit(PROFILE, "vmax = 0.05", "vmx = 0.05"), SIM,
     ("{path}", "vmx", "unknown key")),
    ("profile-leaves-soft-limits", "profile", edit(PROFILE, "target = 0.01", "target = 0.5"), SIM_FULL,
     ("{path}", "axis x", "position", "soft limits [-0.1, 0.1]", "axes.x.limits.position_m", "nothing moved")),
    ("profile-longer-than-a-run-records", "profile", edit(DWELL, "duration = 0.5", "duration = 1e12"),
     SIM_FULL, ("{path}", "duration", "1e+12 s", "2147483647 cycles")),
    ("profile-unplannable-limits", "profile", edit(PROFILE, "vmax = 0.05", "vmax = 1e-300"), SIM,
     ("{path}", "vmax", "ruckig cannot plan")),
    # -- plants (--plant FILE) ---------------------------------------------------------------------------
    ("plant-toml-syntax", "plant", edit(PLANT, "mass = 88.08", "mass = 88.08.1"), SIM, ("{path}", "not valid TOML")),
    ("plant-mass-wrong-type", "plant", edit(PLANT, "mass = 88.08", 'mass = "heavy"'), SIM,
     ("{path}", "params.mass", "'heavy'")),
    ("plant-mass-negative", "plant", edit(PLANT, "mass = 88.08", "mass = -88.08"), SIM,
     ("{path}", "params.mass", "-88.08")),
    ("plant-missing-body", "plant", PLANT[: PLANT.index("[params]")], SIM, ("{path}", "params", "missing")),
    ("plant-missing-parameter", "plant", edit(PLANT, "c_neg = 530.6", "# c_neg"), SIM,
     ("{path}", "params.c_neg", "missing")),
    ("plant-unknown-model", "plant", edit(PLANT, 'model = "rigid"', 'model = "flexible"'), SIM,
     ("{path}", "model", "'flexible'")),
    ("plant-model-wrong-type", "plant", edit(PLANT, 'model = "rigid"', 'model = ["rigid"]'), SIM,
     ("{path}", "model", "['rigid']")),
    ("plant-unknown-effect", "plant", PLANT + '\n[[effects]]\nname = "wobble"\n', SIM,
     ("{path}", "effects[0].name", "'wobble'")),
    ("plant-effect-name-wrong-type", "plant", PLANT + '\n[[effects]]\nname = ["backlash"]\n', SIM,
     ("{path}", "effects[0].name", "['backlash']")),
    ("plant-effect-out-of-range", "plant", PLANT + '\n[[effects]]\nname = "backlash"\nwidth = -2e-5\n', SIM,
     ("{path}", "effects[0].width", "> 0")),
    # -- trace files (summary FILE, plot FILE --out PNG) ------------------------------------------------
    ("trace-truncated-mid-row", "trace", TRACE[: TRACE.rindex(",0.000002500")], ["summary"],
     ("{path}", "data row 4", "pos_m")),
    ("trace-garbled-number", "trace", edit(TRACE, "0.000000500", "0.0000o0500"), ["plot"],
     ("{path}", "column pos_m", "data row 2", "'0.0000o0500'")),
    ("trace-extra-field", "trace", edit(TRACE, "10.000000\n", "10.000000,5\n"), ["summary"],
     ("{path}", "data row 2", "5 fields", "time_s,ref_m,pos_m,effort")),
    ("trace-missing-column", "trace", without_column(TRACE, 2), ["summary"],
     ("{path}", "pos_m")),
    ("trace-time-not-increasing", "trace", edit(TRACE, "0.002000,", "0.000500,"), ["plot"],
     ("{path}", "column time_s", "data row 3")),
    ("trace-nan-position", "trace", edit(TRACE, "0.000001500", "nan"), ["summary"],
     ("{path}", "column pos_m", "data row 3")),
    ("trace-dt-garbled", "trace", edit(TRACE, "# dt_s: 0.001", "# dt_s: fast"), ["summary"],
     ("{path}", "dt_s", "'fast'")),
    ("trace-one-row-no-dt", "trace", "time_s,ref_m,pos_m,effort\n0.0,0.0,0.0,0.0\n", ["summary"],
     ("{path}", "dt_s", "fewer than two rows")),
    ("trace-empty", "trace", "", ["summary"], ("{path}", "no column row", "time_s")),
    ("trace-header-only", "trace", TRACE[: TRACE.index("0.000000,")], ["plot"], ("{path}", "no data rows")),
    # -- the drive: its EDS and its answers ------------------------------------------------------------
    ("eds-missing-0x6071", "eds", eds_without("6071"), BUS, ("{name}", "axis x", "0x6071", "torque setpoint")),
    ("eds-missing-file", "eds", None, BUS, ("{name}", "axis x", "cannot be read")),
    ("eds-not-an-eds", "eds", "this is not an EDS\n", BUS, ("{name}", "axis x", "cannot be read")),
    # the drive on the bus is not the one the EDS describes (0x1018 vendor)
    ("eds-of-another-drive", "eds", re.sub(r"(?m)^VendorNumber=\S+", "VendorNumber=0x12345678", EDS), BUS,
     ("node 1", "identity", "expects vendor 0x12345678")),
    # the drive answers an SDO write with an abort (injected into the emulated drive)
    ("sdo-abort-injected", "args", None, [*BUS, "--fault", "sdo-abort:index=0x6060"],
     ("axis x", "node 1", "SDO 0x6060 aborted")),
    # the drive (impersonating this EDS) takes modes up to 8 in 0x6060 although 0x6502 says cst: it aborts the
    # write of mode 10 while the master configures it
    ("sdo-abort-while-configuring", "eds", edit(EDS, "[6060]\nParameterName=Modes of operation\nObjectType=0x7\n"
                                                "DataType=0x0002", "[6060]\nParameterName=Modes of operation\n"
                                                "ObjectType=0x7\nDataType=0x0002\nHighLimit=8"), BUS,
     ("node 1", "0x6060", "aborted")),
    # -- command-line values ----------------------------------------------------------------------------
    ("fault-spec-zero-cycles", "args", None, [*BUS, "--fault", "tpdo-lost:cycles=0@1"], ("--fault", "cycles")),
    ("fault-spec-unknown-kind", "args", None, [*BUS, "--fault", "brownout@1"], ("--fault", "'brownout'")),
    ("duration-longer-than-a-run-records", "args", None, [*SIM, "--duration", "1e12"],
     ("--duration", "1e+12 s", "2147483647 cycles")),
    # issue 18: values that gave tracebacks (or, x,x under --sim, a wrong run with exit 0)
    ("noise-negative", "args", None, [*SIM, "--noise", "-1"], ("--noise", "-1", ">= 0")),
    ("noise-nan", "args", None, [*SIM, "--noise", "nan"], ("--noise", "nan", "finite")),
    ("axis-empty", "args", None, [*SIM, "--axis", ""], ("--axis", "no axis name")),
    ("axis-only-a-comma", "args", None, [*SIM, "--axis", ","], ("--axis", "','", "empty axis name")),
    ("axis-twice", "args", None, [*SIM, "--axis", "x,x"], ("--axis", "'x,x'", "named twice")),
    ("axis-twice-on-the-bus", "args", None, [*BUS, "--axis", "x,y,x"], ("--axis", "named twice")),
    ("seed-negative", "args", None, [*SIM, "--seed", "-1"], ("--seed", "-1")),
    ("fault-emcy-code-too-large", "args", None, [*BUS, "--fault", "emcy-fault:code=99999999@0.01"],
     ("--fault", "code", "0..0xFFFF", "99999999")),
    ("fault-encoder-jump-infinite", "args", None, [*BUS, "--fault", "encoder-glitch:jump=inf@0.01"],
     ("--fault", "jump", "inf")),
    ("fault-encoder-jump-beyond-counts", "args", None, [*BUS, "--fault", "encoder-glitch:jump=1e300@0.01"],
     ("--fault", "jump", "at most 1 m")),
    ("bus-log-unknown-format", "args", None, [*BUS, "--bus-log", "/tmp/frames.mf4"], ("--bus-log", "format")),
    ("bus-log-missing-folder", "args", None, [*BUS, "--bus-log", "/nonexistent-drivectl/frames.asc"],
     ("--bus-log", "/nonexistent-drivectl", "does not exist")),
    ("config-axis-name-escapes", "config", edit(CONFIG, "[axes.x]\nnode_id = 1", '[axes."../../escaped"]\nnode_id = 1')
     .replace("[axes.x.", '[axes."../../escaped".'), SIM, ("{path}", "axes.'../../escaped'", "letters, digits")),
    ("config-max-lost-cycles-too-many", "config", edit(CONFIG, "max_lost_cycles = 3 ", "max_lost_cycles = 65535 "),
     BUS, ("{path}", "axes.x.max_lost_cycles", "0..10", "65535")),
    ("trace-duplicate-column", "trace", TRACE.replace("pos_m,effort\n", "pos_m,effort,pos_m\n").replace(
        "0\n", "0,0.047\n"), ["summary"], ("{path}", "'pos_m' appears twice")),
    ("trace-dt-wrong", "trace", edit(TRACE, "# dt_s: 0.001", "# dt_s: 1"), ["summary"],
     ("{path}", "dt_s", "time column steps 0.001")),
    # -- config init over an existing file ---------------------------------------------------------------
    ("config-init-over-existing", "init", "# my machine, hand-tuned\ncycle_s = 0.002\n", [],
     ("{path}", "exists", "--force")),
]

PARAMS = [pytest.param(*c[1:], id=c[0]) for c in CASES]


def _prepare(tmp_path: Path, kind: str, text: str | None, argv: list[str]) -> tuple[list[str], Path, Path]:
    """(full argv, the bad file, the --out folder)."""
    out = tmp_path / "out"
    suffix = {"trace": ".csv", "eds": ".eds"}.get(kind, ".toml")
    bad = tmp_path / f"bad-{kind}{suffix}"
    if text is not None:
        bad.write_text(text)
    if kind == "config":
        return ["--config", str(bad), *argv, "--out", str(out)], bad, out
    if kind == "profile":
        return [*argv, "--profile", str(bad), "--out", str(out)], bad, out
    if kind == "plant":
        return [*argv, "--plant", str(bad), "--out", str(out)], bad, out
    if kind == "trace":
        extra = ["--out", str(out / "plot.png")] if argv[0] == "plot" else []
        return [argv[0], str(bad), *extra], bad, out
    if kind == "eds":
        cfg = tmp_path / "machine.toml"
        cfg.write_text(config_with_eds(bad))
        return ["--config", str(cfg), *argv, "--out", str(out)], bad, out
    if kind == "args":  # no file: the command line itself is wrong
        return [*argv, "--out", str(out)], bad, out
    assert kind == "init"
    return ["config", "init", str(bad)], bad, out


def test_the_matrix_is_big_enough():
    assert len(CASES) >= 34 and len({c[0] for c in CASES}) == len(CASES)


@pytest.mark.parametrize(("kind", "text", "argv", "fragments"), PARAMS)
def test_bad_input(tmp_path, capsys, kind, text, argv, fragments):
    full, bad, out = _prepare(tmp_path, kind, text, argv)
    before = {p: p.read_bytes() for p in tmp_path.rglob("*") if p.is_file()}

    rc = main(full)

    err = capsys.readouterr().err
    assert rc == 2, err
    assert err.endswith("\n") and "Traceback" not in err, err
    lines = err[:-1].split("\n")
    assert len(lines) == 1 and lines[0].startswith("drivectl: ") and lines[0] != "drivectl: ", err
    line = lines[0]
    for fragment in fragments:
        fragment = fragment.replace("{path}", str(bad)).replace("{name}", bad.name)
        assert fragment in line, f"{fragment!r} not in {line!r}"
    # nothing half-written: no output, no temporary, no input touched
    assert not out.exists() or not any(out.iterdir()), sorted(out.rglob("*"))
    assert not [p for p in tmp_path.rglob("*") if p.name.endswith(".tmp")]
    after = {p: p.read_bytes() for p in tmp_path.rglob("*") if p.is_file()}
    assert after == before


# (id, kind, the valid text, argv, whether --out gets files): the inputs the cases edit, unedited
BASES = [
    ("config-bus", "config", CONFIG, BUS, True),
    ("config-sim", "config", CONFIG, SIM, True),
    ("config-sim-z", "config", CONFIG, SIM_Z, True),
    ("profile", "profile", PROFILE, SIM, True),
    ("profile-whole-run", "profile", PROFILE, SIM_FULL, True),
    ("dwell", "profile", DWELL, SIM, True),
    ("plant", "plant", PLANT, SIM, True),
    ("trace-plot", "trace", TRACE, ["plot"], True),
    ("trace-summary", "trace", TRACE, ["summary"], False),
    ("eds", "eds", EDS, BUS, True),
    ("config-init-new-file", "init", None, [], False),
]


@pytest.mark.parametrize(("kind", "text", "argv", "writes"), [pytest.param(*b[1:], id=b[0]) for b in BASES])
def test_the_valid_bases_run(tmp_path, capsys, kind, text, argv, writes):
    """The unedited inputs pass where the cases fail, so each case fails for its own edit."""
    full, bad, out = _prepare(tmp_path, kind, text, argv)
    assert main(full) == 0, capsys.readouterr().err
    assert writes == (out.exists() and any(out.iterdir()))
    assert bad.exists()  # config init wrote its file
    assert not [p for p in tmp_path.rglob("*") if p.name.endswith(".tmp")]


def test_eds_helper_keeps_the_file_readable(tmp_path):
    """The EDS without 0x6077 still reads (canopen), so the master refuses it for the missing object."""
    import canopen

    path = tmp_path / "no-6077.eds"
    path.write_text(eds_without("6077"))
    od = canopen.import_od(str(path), 1)
    assert 0x6077 not in od and 0x6071 in od
