"""Identity 0x1018 as the EDS states it (docs/drives.md "Identity"): the emulated drive answers [DeviceInfo]
where 0x1018 carries no usable default; the boot compares only what the configuration asks for
(``identity = "vendor+product" | "vendor" | "revision" | "off"``); a mismatch says what the device answered,
what is expected and the one line to change."""

from __future__ import annotations

import re
import sys
from pathlib import Path

import canopen
import pytest

from drivectl.driver import cia402
from drivectl.driver.axis import AxisConfigError
from drivectl.driver.capabilities import DriveRefused
from drivectl.machine.build import open_machine
from drivectl.machine.config import ConfigError, load_config
from drivectl.plant_emulator.node402 import EMULATED_DRIVE_EDS
from drivectl.tools.cli.main import main

sys.path.insert(0, str(Path(__file__).resolve().parents[1] / "bench"))
from drives import eds_dir  # noqa: E402

VENDOR, PRODUCT, REVISION = 0x00D71C70, 0x00030923, 0x00020001


def _eds(tmp_path: Path, *, defaults: dict[int, int | None], info: dict[str, int | None],
         name: str = "d.eds") -> Path:
    """The emulated drive's EDS with 0x1018:1-3 defaults and [DeviceInfo] numbers as given (None: left out)."""
    od = canopen.import_od(str(EMULATED_DRIVE_EDS), 1)
    for sub, value in defaults.items():
        var = od[cia402.IDENTITY].subindices[sub]
        var.default, var.default_raw = value, None
    for key, value in info.items():
        setattr(od.device_information, key, value)
    path = tmp_path / name
    canopen.export_od(od, str(path), doc_type="eds")
    if info.get("product_number", 1) is None:  # the exporter writes an unset number as 0: leave the key out
        path.write_text("".join(ln for ln in path.read_text().splitlines(keepends=True)
                                if not ln.startswith("ProductNumber=")))
    return path


def _init(tmp_path: Path, eds: Path, extra: str = "") -> Path:
    cfg = tmp_path / "m.toml"
    assert main(["config", "init", str(cfg), "--eds", str(eds), "--force"]) == 0
    if extra:  # in place of the starter's own line of that key
        key = extra.split("=")[0].strip()
        text = re.sub(rf"(?m)^{key} = .*\n", "", cfg.read_text())
        cfg.write_text(text.replace("[axes.x]\n", "[axes.x]\n" + extra, 1))
    # a unique virtual channel per test
    cfg.write_text(cfg.read_text().replace('channel = "drivectl"', f'channel = "identity-{tmp_path.name}"'))
    return cfg


def _boot(cfg: Path):
    with open_machine(load_config(cfg), ["x"]) as m:
        return m.axes["x"].identity_answered, m.axes["x"].identity


def test_a_1018_without_defaults_answers_device_info_and_boots(tmp_path):
    eds = _eds(tmp_path, defaults={1: None, 2: 0, 3: None},
               info={"vendor_number": VENDOR, "product_number": PRODUCT, "revision_number": REVISION})
    text = _init(tmp_path, eds).read_text()
    assert f"vendor_id = 0x{VENDOR:08X}" in text and f"product_code = 0x{PRODUCT:08X}" in text
    answered, want = _boot(tmp_path / "m.toml")
    assert answered == (VENDOR, PRODUCT, REVISION)
    assert (want.vendor_id, want.product_code, want.revision) == (VENDOR, PRODUCT, None)


def test_device_info_without_product_number_checks_no_product(tmp_path):
    eds = _eds(tmp_path, defaults={2: None}, info={"vendor_number": VENDOR, "product_number": None})
    assert "ProductNumber" not in eds.read_text()
    cfg = _init(tmp_path, eds)
    text = cfg.read_text()
    assert "states no ProductNumber: product not checked" in text and "product_code =" not in text
    answered, want = _boot(cfg)
    assert want.product_code is None and want.vendor_id == VENDOR and answered[0] == VENDOR


def test_a_revision_mismatch_is_refused_only_when_the_revision_is_asked(tmp_path):
    # the drive answers revision 0x00010000 (its 0x1018:3), [DeviceInfo] declares another
    eds = _eds(tmp_path, defaults={}, info={"revision_number": REVISION})
    answered, _ = _boot(_init(tmp_path, eds))
    assert answered[2] == 0x00010000
    cfg = _init(tmp_path, eds, extra='identity = "revision"\n')
    with pytest.raises(AxisConfigError) as exc:
        _boot(cfg)
    msg = str(exc.value)
    assert "the device answered vendor 0x00D71C70, product 0x00000402, revision 0x00010000" in msg
    assert f"expects vendor 0x00D71C70, product 0x00000402, revision 0x{REVISION:08X} (revision differs)" in msg
    assert f'set identity = "vendor+product" under [axes.x] in {cfg}' in msg and "\n" not in msg


def test_vendor_only_boots_a_sibling_product_that_the_default_refuses(tmp_path, capsys):
    eds = _eds(tmp_path, defaults={}, info={"product_number": PRODUCT})  # the drive answers 0x402
    cfg = _init(tmp_path, eds)
    # the CLI: one line, exit 2, naming answered, expected and the line to change
    assert main(["--config", str(cfg), "doctor", "--axis", "x"]) == 2
    err = capsys.readouterr().err.strip().splitlines()
    assert len(err) == 1 and "answered vendor 0x00D71C70, product 0x00000402" in err[0]
    assert f"product 0x{PRODUCT:08X} (product differs)" in err[0]
    assert f'set identity = "vendor" under [axes.x] in {cfg}' in err[0]
    cfg = _init(tmp_path, eds, extra='identity = "vendor"\n')
    answered, want = _boot(cfg)
    assert answered[1] == 0x402 and want.product_code is None and want.vendor_id == VENDOR
    off = _init(tmp_path, _eds(tmp_path, defaults={}, info={"vendor_number": 0x12345678}), extra='identity = "off"\n')
    answered, want = _boot(off)
    assert answered[0] == VENDOR and (want.vendor_id, want.product_code) == (None, None)


def test_doctor_prints_answered_and_expected(tmp_path):
    from drivectl.driver.drive_report import drive_lines  # the drive section of `drivectl doctor --axis`

    cfg = _init(tmp_path, _eds(tmp_path, defaults={}, info={}))
    with open_machine(load_config(cfg), ["x"]) as m:
        lines = dict(drive_lines(m.axes["x"]))
    assert lines["identity answered"].startswith("vendor 0x00D71C70, product 0x00000402, revision 0x00010000")
    assert lines["identity expected"] == f"vendor 0x00D71C70, product 0x00000402 ({cfg})"


@pytest.mark.parametrize("line, says", [
    ('identity = "product"\n', "axes.x.identity: expected one of vendor+product, vendor, revision, off"),
    ("vendor_id = -1\n", "axes.x.vendor_id: expected a 32-bit unsigned integer"),
    ('product_code = "0x402"\n', "axes.x.product_code: expected a 32-bit unsigned integer"),
])
def test_a_bad_identity_key_is_one_line_naming_the_field_and_the_file(tmp_path, capsys, line, says):
    cfg = _init(tmp_path, _eds(tmp_path, defaults={}, info={}), extra=line)
    with pytest.raises(ConfigError, match=rf"{cfg}: {says}".replace("+", r"\+").replace("(", r"\(")):
        load_config(cfg)
    assert main(["--config", str(cfg), "trace", "--axis", "x"]) == 2
    err = capsys.readouterr().err.strip().splitlines()
    assert len(err) == 1 and str(cfg) in err[0] and says in err[0]


# -- every real drive's EDS: up, or refused for what it lacks, never for its identity -------------------------
EDS = eds_dir()


@pytest.mark.skipif(EDS is None, reason="no shared/eds folder")
@pytest.mark.parametrize("name", sorted(p.name for p in EDS.glob("*.eds")) if EDS is not None else [])
def test_every_real_eds_boots_or_is_refused_never_for_its_identity(tmp_path, name, capsys):
    cfg = tmp_path / "m.toml"
    try:
        rc = main(["config", "init", str(cfg), "--eds", str(EDS / name)])
    except DriveRefused:  # pragma: no cover - the CLI says it in one line
        rc = 2
    err = capsys.readouterr().err
    if rc != 0:
        assert rc == 2 and "identity" not in err
        return  # refused for what it lacks (one line, exit 2)
    cfg.write_text(cfg.read_text().replace('channel = "drivectl"', f'channel = "identity-{tmp_path.name}"'))
    od = canopen.import_od(str(EDS / name), 1)
    try:
        answered, want = _boot(cfg)
    except (AxisConfigError, ConfigError) as exc:
        assert "identity" not in str(exc), str(exc)
        return  # refused for what it lacks
    info = od.device_information
    # the check compares the [DeviceInfo] the EDS states (0: stated nothing) and the drive answered it
    assert want.revision is None and want.product_code == (info.product_number or None)
    assert answered[0] is None or want.vendor_id in (None, answered[0])
    assert want.revision is None and (want.vendor_id or None) == (info.vendor_number or None)


def test_shell_scan_says_what_the_drive_answered_under_a_vendor_only_check(tmp_path, monkeypatch, capsys):
    import io

    cfg = _init(tmp_path, _eds(tmp_path, defaults={}, info={"product_number": PRODUCT}), extra='identity = "vendor"\n')
    monkeypatch.setattr(sys, "stdin", io.StringIO("scan\n"))
    assert main(["--config", str(cfg), "shell", "--axis", "x"]) == 0
    assert "x: node 1, vendor 0x00D71C70, product 0x00000402, revision 0x00010000" in capsys.readouterr().out
