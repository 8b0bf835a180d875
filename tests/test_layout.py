"""Dependencies run one way: omniflow imports no omnisim, mitsuba or validation.

Each check runs in a fresh interpreter (``sys.modules`` of the test process already
holds whatever other tests imported) and lists the modules it finds, so a failure
names the import to remove.
"""

from __future__ import annotations

import json
import pkgutil
import subprocess
import sys
from pathlib import Path

import omniflow

#: Top-level packages omniflow must not pull in.
FORBIDDEN = ("omnisim", "mitsuba", "drjit", "validation")

REPORT = """
import json, sys
print(json.dumps(sorted(m for m in sys.modules if m.split(".")[0] in {forbidden!r})))
"""


def _foreign_modules(code: str, *args: str) -> list[str]:
    """Modules of FORBIDDEN loaded after running ``code`` in a new interpreter."""
    script = code + REPORT.format(forbidden=set(FORBIDDEN))
    p = subprocess.run(
        [sys.executable, "-c", script, *args], capture_output=True, text=True, timeout=120
    )
    assert p.returncode == 0, p.stderr
    return json.loads(p.stdout.strip().splitlines()[-1])


def test_import_omniflow_cli_imports_no_simulator():
    assert _foreign_modules("import omniflow.cli\n") == []


def test_every_omniflow_module_imports_no_simulator():
    names = sorted(m.name for m in pkgutil.iter_modules(omniflow.__path__, "omniflow."))
    assert {"omniflow.cli", "omniflow.dataset", "omniflow.camera"} <= set(names)
    code = "import importlib\n" + "".join(f"importlib.import_module({n!r})\n" for n in names)
    assert _foreign_modules(code) == []


def test_reading_a_dataset_imports_no_simulator(tmp_path):
    """The omniflow command's dataset mode, end to end in one process: the dataset is
    read with omniflow.dataset (importing omnisim.dataset there would fail this)."""
    from omnisim_fakes import write_synthetic_dataset

    ds = write_synthetic_dataset(tmp_path / "ds", frames=2, size=64)
    out = tmp_path / "out"
    code = (
        "import sys\nfrom omniflow.cli import main\nrc = main(sys.argv[1:])\nassert rc == 0, rc\n"
    )
    args = ("--dataset", str(ds), "--frame", "0", "--out", str(out), "--no-pictures")
    assert _foreign_modules(code, *args) == []
    assert (out / "flow.csv").is_file()


def test_the_check_can_fail():
    """The probe does see a simulator module when one is imported."""
    assert _foreign_modules("import omnisim.dataset\n") == ["omnisim", "omnisim.dataset"]


def test_reexports_are_the_same_objects():
    """Old import paths give the objects of the new homes (one definition)."""
    import omniflow.camera
    import omniflow.dataset
    import omnisim.camera
    import omnisim.dataset

    for name in omniflow.dataset.__all__:
        if hasattr(omnisim.dataset, name):
            assert getattr(omnisim.dataset, name) is getattr(omniflow.dataset, name), name
    for name in omnisim.camera.__all__:
        assert getattr(omnisim.camera, name) is getattr(omniflow.camera, name), name
    assert Path(omniflow.dataset.__file__).parent.name == "omniflow"
