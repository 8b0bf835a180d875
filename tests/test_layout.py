"""Dependencies run one way, and the omniflow packages are layered.

* omniflow imports no omnisim, mitsuba or validation. Each check runs in a fresh
  interpreter (``sys.modules`` of the test process already holds whatever other tests
  imported) and lists the modules it finds, so a failure names the import to remove.
* Inside omniflow, a package imports only the packages of lower layers (:data:`LAYERS`):
  the paper's equations know nothing of the extensions, nothing imports the commands.
* No import cycles inside a package.
"""

from __future__ import annotations

import ast
import json
import pkgutil
import subprocess
import sys
from pathlib import Path

import omniflow

ROOT = Path(__file__).resolve().parents[1]

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


def _omniflow_modules() -> list[str]:
    """Every module of omniflow, subpackages included."""
    return sorted(m.name for m in pkgutil.walk_packages(omniflow.__path__, "omniflow.") if m.name)


def test_import_omniflow_cli_imports_no_simulator():
    assert _foreign_modules("import omniflow.cli\n") == []


def test_every_omniflow_module_imports_no_simulator():
    names = _omniflow_modules()
    assert {"omniflow.cli.pair", "omniflow.io.dataset", "omniflow.paper.flow"} <= set(names)
    code = "import importlib\n" + "".join(f"importlib.import_module({n!r})\n" for n in names)
    assert _foreign_modules(code) == []


def test_reading_a_dataset_imports_no_simulator(tmp_path):
    """The omniflow command's dataset mode, end to end in one process: the dataset is
    read with omniflow.io.dataset (importing omnisim.dataset there would fail this)."""
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
    found = _foreign_modules("import omnisim.dataset\n")
    assert {"omnisim", "omnisim.dataset"} <= set(found)


def test_omnisim_reexports_the_dataset_contract():
    """omnisim.dataset's names of the contract are omniflow.io.dataset's objects."""
    import omniflow.io.dataset
    import omnisim.dataset

    shared = [n for n in omniflow.io.dataset.__all__ if hasattr(omnisim.dataset, n)]
    assert "open_dataset" in shared
    for name in shared:
        assert getattr(omnisim.dataset, name) is getattr(omniflow.io.dataset, name), name


def test_camera_and_closed_form_scenes_need_no_mitsuba():
    """The sensor model and the closed-form renderer live in omnisim but import no
    Mitsuba, so validation scores camera images without the ``sim`` extra."""
    found = _foreign_modules("import omnisim.camera, omnisim.synthetic\n")
    assert "mitsuba" not in found and "drjit" not in found, found


# -- layers inside omniflow --------------------------------------------------------------

#: Layer of each omniflow package or top-level module; a module imports only modules
#: of its own package or of packages of a strictly lower layer.
LAYERS: dict[str, int] = {
    "omniflow.conventions": 0,
    "omniflow.parallel": 0,
    "omniflow.interrupts": 0,
    "omniflow.input_files": 0,
    "omniflow.geometry": 1,
    "omniflow.io": 1,
    "omniflow.paper": 2,
    "omniflow.solve.pooled_kernels": 2,
    "omniflow.matching": 3,
    "omniflow.config": 4,
    "omniflow.result": 5,
    "omniflow.fit": 6,
    "omniflow.solve": 7,
    "omniflow.applications": 8,
    "omniflow.registration": 8,
    "omniflow.pipeline": 9,
    "omniflow.stream": 10,
    "omniflow.cli": 11,
}

#: Imports that break the layering on purpose, each with its reason.
KNOWN_UPWARD: set[tuple[str, str]] = {
    # geometry.calibration reads colour images through the one luma (to_grey)
    ("omniflow.geometry.calibration", "omniflow.io.imageio"),
    # io.dataset builds the dataset's Rig from dataset.json
    ("omniflow.io.dataset", "omniflow.geometry.rig"),
    # flow_shading_where="moving" finds the movers as odometry's outliers, grouped
    ("omniflow.solve.shading", "omniflow.applications.navigation"),
    ("omniflow.solve.shading", "omniflow.applications.regions"),
}


def _group(module: str) -> str:
    """The entry of :data:`LAYERS` a module belongs to."""
    parts = module.split(".")
    for n in range(len(parts), 0, -1):
        if ".".join(parts[:n]) in LAYERS:
            return ".".join(parts[:n])
    raise AssertionError(f"{module}: not in LAYERS; add its package to tests/test_layout.py")


def test_layers_cover_every_module():
    for name in _omniflow_modules():
        if name != "omniflow":
            _group(name)


def test_each_package_imports_only_lower_layers():
    bad = []
    for module, deps in _import_graph("omniflow").items():
        if module == "omniflow":
            continue
        here = _group(module)
        for dep in deps:
            there = _group(dep)
            if there == here or (module, dep) in KNOWN_UPWARD:
                continue
            if LAYERS[there] >= LAYERS[here]:
                bad.append(f"{module} imports {dep}")
    assert bad == []


def test_the_paper_imports_no_extension():
    """omniflow.paper: only conventions, the rig and itself."""
    for module, deps in _import_graph("omniflow").items():
        if module.startswith("omniflow.paper"):
            assert {_group(d) for d in deps} <= {
                "omniflow.conventions",
                "omniflow.geometry",
                "omniflow.paper",
            }, module


def test_nothing_imports_the_commands():
    for module, deps in _import_graph("omniflow").items():
        if not module.startswith("omniflow.cli"):
            assert not any(d.startswith("omniflow.cli") for d in deps), module


def test_the_layer_check_can_fail():
    assert _group("omniflow.paper.flow") == "omniflow.paper"
    assert LAYERS[_group("omniflow.solve.gain")] > LAYERS[_group("omniflow.paper.dct")]


# -- no import cycles inside a package ------------------------------------------------

#: Import cycles left on purpose, each with the reason (none: render <-> groundtruth was
#: broken by omnisim.mitsuba_scene, job <-> distributed by omnisim.meta).
KNOWN_CYCLES: set[frozenset[str]] = set()


def _module_name(package: str, path: Path) -> str:
    rel = path.relative_to(ROOT).with_suffix("")
    parts = list(rel.parts)
    if parts[-1] == "__init__":
        parts = parts[:-1]
    return ".".join(parts)


def _import_graph(package: str) -> dict[str, set[str]]:
    """Module -> the package's modules it imports anywhere (top level or in a function),
    subpackages included; ``from a.b import c`` counts ``a.b.c`` when that is a module."""
    graph: dict[str, set[str]] = {}
    for path in sorted((ROOT / package).rglob("*.py")):
        name = _module_name(package, path)
        is_pkg = path.stem == "__init__"
        deps: set[str] = set()
        for node in ast.walk(ast.parse(path.read_text(encoding="utf-8"))):
            if isinstance(node, ast.Import):
                deps.update(a.name for a in node.names)
            elif isinstance(node, ast.ImportFrom):
                if node.level:
                    base = name.split(".")[: len(name.split(".")) - node.level + is_pkg]
                    mod = ".".join(base + ([node.module] if node.module else []))
                else:
                    mod = node.module or ""
                deps.add(mod)
                deps.update(f"{mod}.{a.name}" for a in node.names)
        graph[name] = {d for d in deps if d.startswith(f"{package}.") and d != name}
    for deps in graph.values():
        resolved = set()
        for d in deps:
            while d not in graph and "." in d:
                d = d.rsplit(".", 1)[0]  # a name imported from a module: the module
            if d in graph:
                resolved.add(d)
        deps.clear()
        deps.update(resolved)
    for name, deps in graph.items():
        deps.discard(name)
        # a package's __init__ counted as imported by its own modules is not a cycle
        deps.difference_update({d for d in deps if name.startswith(d + ".")})
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
