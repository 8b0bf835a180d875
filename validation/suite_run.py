"""``omnivalidate suite``: render what is missing, score every method on every scene of a
suite, and write the leaderboard. Resumable: run the same command again after an
interruption and it renders only the missing frames and scores only the scenes not
scored yet with the same methods.

Layout of ``--out DIR``::

    DIR/scenes/NAME.toml         each scene's TOML (generated, or the file's text)
    DIR/renders/NAME/            its rendered dataset (omnisim's render job)
    DIR/scenes/NAME/             its omnivalidate report (summary.json, report.html, ...)
    DIR/state/NAME.json          what the report scored (methods, outputs): the resume key
    DIR/leaderboard.md, .html, .csv, .json

Every file is written to a temporary name and renamed into place.
"""

from __future__ import annotations

import json
import time
from collections.abc import Callable, Mapping, Sequence
from dataclasses import dataclass, field
from pathlib import Path, PurePosixPath
from typing import Any

from omniflow.io.imageio import OutputError, atomic_write_text

from .inputs import InputError
from .suite import Suite, SuiteError, SuiteScene, scene_text

__all__ = [
    "SuiteMethods",
    "claim_run_folder",
    "method_catalogue",
    "resolve_methods",
    "run_suite",
    "score_dataset",
]

#: The top-level names ``omnivalidate suite`` writes into its --out.
SUITE_NAMES = ("leaderboard.md", "leaderboard.html", "leaderboard.csv", "leaderboard.json",
               "scenes", "renders", "state")  # fmt: skip


def _legacy_run(folder: Path) -> bool:
    """A suite or sweep run from before markers: its leaderboard.json / sweep.json, or the
    state files of an unfinished one."""
    from omniflow.io import ownership

    for name, fmt in (("leaderboard.json", "omnivalidate-leaderboard/"),
                      ("sweep.json", "omnivalidate-sweep/")):  # fmt: skip
        body = ownership.read_json(folder / name)
        if isinstance(body, dict) and str(body.get("format", "")).startswith(fmt):
            return True
    return any((folder / "state").glob("*.json")) or any((folder / "points").glob("*/state.json"))


def claim_run_folder(out: Path, prog: str, names: Sequence[str]) -> None:
    """Refuse (ForeignPathError, one line) an --out that is not this command's: a folder
    with files but no marker, or a top-level name the command does not write; then mark
    it. What lies inside its own subfolders is checked by the steps that write them (the
    render job, the report)."""
    from omniflow.io import ownership

    def owned(rel: PurePosixPath) -> bool:
        return len(rel.parts) > 1 or rel.name in names or rel.name == ownership.MARKER

    try:
        ownership.claim(out, prog=prog, owned=owned, legacy=_legacy_run)
    except OutputError as exc:  # a user's file in the way, or --out is a file
        raise InputError(f"--out {exc}") from None
    out.mkdir(parents=True, exist_ok=True)
    if not ownership.has_marker(out):
        ownership.write_marker(out, prog)


@dataclass
class SuiteMethods:
    """What a suite run scores: omniflow rows, baselines, and external outputs
    (name -> a folder with one subfolder per scene, in ``--method-output`` layout)."""

    rows: list[tuple[str, Any]]
    baselines: list[str]
    external: dict[str, Path] = field(default_factory=dict)

    def key(self) -> dict[str, Any]:
        """JSON-able description, compared on resume (with the rig file of a row
        registered by a card, ``--registration FILE``)."""
        key = {
            "omniflow": [name for name, _ in self.rows],
            "baselines": list(self.baselines),
            "external": {k: str(Path(v).resolve()) for k, v in self.external.items()},
        }
        cards = {n: c.rig_file for n, c in self.rows if getattr(c, "registration", "") == "card"}
        if cards:
            key["registration_rig"] = cards
        return key


def method_catalogue() -> tuple[list[tuple[str, Any]], list[tuple[str, Any]]]:
    """(every omniflow row a suite can name, the rows it scores by default).

    The default rows are omniflow's default configuration, its dense preset and the
    paper's configuration; the others are the one-choice-at-a-time variants."""
    from omniflow.cli.common import config_from_settings
    from omniflow.pipeline import OmniFlowConfig

    from .variants import omniflow_variants, variant_name

    rows = omniflow_variants("oat", true_matches=False)
    dense = config_from_settings("dense")
    if all(cfg != dense for _, cfg in rows):
        rows.append((variant_name(dense), dense))
    paper = OmniFlowConfig.paper()
    defaults = [rows[0]] + [r for r in rows[1:] if r[1] in (dense, paper)]
    return rows, defaults


def resolve_methods(
    names: Sequence[str] | None,
    external: Mapping[str, Path] | None = None,
    registration: str | None = None,
) -> SuiteMethods:
    """The rows for ``--methods`` (None: omniflow's default, dense and paper rows and
    every baseline), each once per ``--registration`` choice
    (:func:`validation.variants.with_registration`); InputError (one line) for an
    unknown name or registration."""
    from . import baselines as bl
    from .variants import with_registration

    rows, defaults = method_catalogue()
    external = dict(external or {})
    if names is None:
        return SuiteMethods(with_registration(defaults, registration), list(bl.BASELINES),
                            external)  # fmt: skip
    by_name = dict(rows)
    picked: list[tuple[str, Any]] = []
    base: list[str] = []
    for n in names:
        if n in by_name:
            picked.append((n, by_name[n]))
        elif n in bl.BASELINES:
            base.append(n)
        else:
            raise InputError(
                f"--methods: unknown method {n!r}; expected some of "
                f"{[r for r, _ in rows] + list(bl.BASELINES)}"
            )
    return SuiteMethods(with_registration(picked, registration), base, external)


def _write_scene(scene: SuiteScene, out: Path) -> Path:
    """Write the scene's TOML to DIR/scenes/NAME.toml (kept if already there and the
    same); returns the file to render from."""
    text = scene_text(scene)
    path = out / "scenes" / f"{scene.name}.toml"
    if path.is_file():
        if path.read_text(encoding="utf-8") != text:
            raise SuiteError(
                f"{path}: differs from the suite's scene {scene.name!r} (the suite or the "
                "generator changed since this run); use a new --out"
            )
    else:
        atomic_write_text(path, text)
    # A scene file names its assets relative to itself: render the original.
    return scene.file if scene.file is not None else path


def _render(suite: Suite, scene_file: Path, dataset: Path, scheduler: str | None,
            progress: bool) -> str:  # fmt: skip
    from omnisim.job import render_dataset

    overrides = {
        "frames": suite.frames,
        "render.width": suite.resolution,
        "render.height": suite.resolution,
    }
    res = render_dataset(scene_file, dataset, overrides, scheduler=scheduler, progress=progress)
    return f"{len(res.rendered)} frames rendered, {len(res.skipped)} already there"


def _score(scene: SuiteScene, dataset: Path, report: Path, state: Path, methods: SuiteMethods,
           progress: bool) -> tuple[dict, str]:  # fmt: skip
    """Score the scene (or reuse its report when the same methods scored it)."""
    from .external import ExternalOutput

    external = []
    for name, folder in methods.external.items():
        sub = Path(folder) / scene.name
        if not sub.is_dir():
            raise InputError(
                f"--method-output {name}={folder}: no folder {scene.name}/ for scene "
                f"{scene.name!r}; expected one folder per scene (docs/suite.md)"
            )
        external.append(ExternalOutput(sub, name))
    return score_dataset(dataset, report, state, methods, progress, external=external)


def score_dataset(dataset: Path, report: Path, state: Path, methods: SuiteMethods,
                  progress: bool, key: Mapping[str, Any] | None = None,
                  external: Sequence[Any] = ()) -> tuple[dict, str]:  # fmt: skip
    """Score ``dataset`` into ``report`` (its summary and how: "scored" or "scored
    before"); the report is reused when ``state`` records the same ``key`` (default:
    the methods), so an interrupted run resumes."""
    from .report import check_out_dir, write_report
    from .runner import run_validation

    key = dict(key) if key is not None else methods.key()
    summary_path = report / "summary.json"
    if state.is_file() and summary_path.is_file():
        try:
            same = json.loads(state.read_text(encoding="utf-8")) == key
            if same:
                return json.loads(summary_path.read_text(encoding="utf-8")), "scored before"
        except ValueError:  # a damaged file: score again
            pass
    check_out_dir(report)
    results = run_validation(
        dataset,
        variants=methods.rows,
        baselines=methods.baselines,
        progress=progress,
        external=list(external),
    )
    summary = write_report(results, report, command=None)
    atomic_write_text(state, json.dumps(key, indent=1) + "\n")
    return summary, "scored"


def run_suite(
    suite: Suite,
    out: str | Path,
    *,
    split: str,
    methods: SuiteMethods,
    scheduler: str | None = None,
    progress: bool = True,
    log: Callable[[str], None] = print,
    command: str | None = None,
) -> dict[str, Any]:
    """Render, score and rank every scene of ``split``; returns the leaderboard dict.

    Raises SuiteError, InputError and the render job's errors (SceneError, DatasetError,
    ResourceError, ClusterError) with one-line messages; what is finished stays on disk.
    """
    from omniflow.io.jsonio import jsonable

    from .leaderboard import leaderboard, write_leaderboard

    out = Path(out)
    scenes = suite.select(split)
    if not scenes:
        raise SuiteError(f"{suite.path}: no scene in split {split!r}")
    claim_run_folder(out, "omnivalidate suite", SUITE_NAMES)
    done: list[tuple[str, str, Mapping[str, Any]]] = []
    for k, scene in enumerate(scenes, 1):
        t0 = time.perf_counter()
        tag = f"omnivalidate suite {suite.name}: [{k}/{len(scenes)}] {scene.name}"
        scene_file = _write_scene(scene, out)
        log(f"{tag}: rendering {suite.frames} frames at {suite.resolution} px")
        dataset = out / "renders" / scene.name
        log(f"{tag}: {_render(suite, scene_file, dataset, scheduler, progress)}")
        log(f"{tag}: scoring {len(methods.rows) + len(methods.baselines) + len(methods.external)}"
            " methods")  # fmt: skip
        report = out / "scenes" / scene.name
        summary, how = _score(scene, dataset, report, out / "state" / f"{scene.name}.json",
                              methods, progress)  # fmt: skip
        done.append((scene.name, scene.split, summary))
        log(f"{tag}: {how} in {time.perf_counter() - t0:.1f} s; report {report / 'report.html'}")
    board = leaderboard(
        done,
        suite={
            "name": suite.name,
            "path": str(suite.path),
            "description": suite.description,
            "split": split,
            "frames": suite.frames,
            "resolution": suite.resolution,
            "methods": methods.key(),
        },
    )
    board = jsonable(board)
    write_leaderboard(board, out, command=command)
    return board
