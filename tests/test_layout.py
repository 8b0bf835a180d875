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
    from tests.helpers.fakes import write_synthetic_dataset

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


# -- no import cycles inside a package ------------------------------------------------

#: Import cycles left on purpose, each with the reason (none: render <-> groundtruth was
#: broken by omnisim.mitsuba_scene, job <-> distributed by omnisim.meta).
KNOWN_CYCLES: set[frozenset[str]] = set()


def _import_graph(package: str) -> dict[str, set[str]]:
    """Module -> the package's modules it imports anywhere (top level or in a function)."""
    import ast

    root = Path(__file__).resolve().parents[1] / package
    graph: dict[str, set[str]] = {}
    for path in sorted(root.glob("*.py")):
        name = f"{package}.{path.stem}" if path.stem != "__init__" else package
        deps: set[str] = set()
        for node in ast.walk(ast.parse(path.read_text(encoding="utf-8"))):
            if isinstance(node, ast.Import):
                deps.update(a.name for a in node.names)
            elif isinstance(node, ast.ImportFrom) and node.module and node.level == 0:
                deps.add(node.module)
                deps.update(f"{node.module}.{a.name}" for a in node.names)
            elif isinstance(node, ast.ImportFrom) and node.level == 1:
                mods = [node.module] if node.module else [a.name for a in node.names]
                deps.update(f"{package}.{m}" for m in mods)
        graph[name] = {d for d in deps if d.startswith(f"{package}.") and d != name}
    for deps in graph.values():
        deps.intersection_update(graph)
    return graph


def _cycles(graph: dict[str, set[str]]) -> set[frozenset[str]]:
    """The strongly connected components of more than one module (Tarjan)."""
    index: dict[str, int] = {}
    low: dict[str, int] = {}
    stack: list[str] = []
    found: set[frozenset[str]] = set()

    def visit(v: str) -> None:
        index[v] = low[v] = len(index)
        stack.append(v)
        for w in graph[v]:
            if w not in index:
                visit(w)
                low[v] = min(low[v], low[w])
            elif w in stack:
                low[v] = min(low[v], index[w])
        if low[v] == index[v]:
            comp = set()
            while True:
                w = stack.pop()
                comp.add(w)
                if w == v:
                    break
            if len(comp) > 1:
                found.add(frozenset(comp))

    for v in graph:
        if v not in index:
            visit(v)
    return found


def test_cycle_finder_sees_a_cycle():
    graph = {"p.a": {"p.b"}, "p.b": {"p.c"}, "p.c": {"p.a"}, "p.d": {"p.a"}}
    assert _cycles(graph) == {frozenset({"p.a", "p.b", "p.c"})}
    assert _cycles({"p.a": {"p.b"}, "p.b": set()}) == set()


def test_job_and_distributed_do_not_import_each_other():
    graph = _import_graph("omnisim")
    assert "omnisim.job" not in graph["omnisim.distributed"]
    assert "omnisim.meta" in graph["omnisim.distributed"] and "omnisim.meta" in graph["omnisim.job"]


def test_no_import_cycles_but_the_known_ones():
    for package in ("omniflow", "omnisim", "validation"):
        assert _cycles(_import_graph(package)) <= KNOWN_CYCLES, package
