"""Procedural scenes: ``generate_scene(family, seed)`` writes an ordinary scene file.

Each family (:data:`FAMILIES`) is a module with ``build(draw) -> (table, notes)``; the
ranges it draws from are listed key by key in ``docs/generator.md``. A scene is drawn
with ``numpy.random.Generator(PCG64(seed))``, written as TOML with fixed decimals
(:mod:`omnisim.generate.toml_text`), and loaded with :func:`omnisim.scene.load_scene`,
which checks placement. When the loader refuses it, attempt k = 1, 2, ... draws again
from ``PCG64(SeedSequence([seed, k]))``, up to :data:`MAX_ATTEMPTS`; so the generator
never returns a scene the loader refuses, and the same (family, seed) gives the same
bytes. Nothing here imports Mitsuba.
"""

from __future__ import annotations

import os
import tempfile
from collections.abc import Callable, Iterable
from pathlib import Path
from typing import Any

import numpy as np

from omnisim.generate import common, corridor, hall, outdoor, room
from omnisim.generate.toml_text import to_toml

__all__ = [
    "FAMILIES",
    "GENERATOR_VERSION",
    "MAX_ATTEMPTS",
    "GenerateError",
    "generate_batch",
    "generate_scene",
    "scene_name",
    "write_scene",
]

#: Bumped whenever the text generated for any (family, seed) changes.
GENERATOR_VERSION = "1"
#: Draws tried per (family, seed) before giving up (measured: see docs/generator.md).
MAX_ATTEMPTS = 50
#: Largest seed accepted (NumPy takes any non-negative integer; this keeps names short).
MAX_SEED = 2**63 - 1

_BUILDERS: dict[str, Callable[[common.Draw], tuple[dict[str, Any], list[str]]]] = {
    "room": room.build,
    "corridor": corridor.build,
    "hall": hall.build,
    "outdoor": outdoor.build,
}
#: The scene families, in a fixed order.
FAMILIES: tuple[str, ...] = tuple(_BUILDERS)


class GenerateError(ValueError):
    """Bad generator input (unknown family, bad seed), or no loadable draw was found."""


def scene_name(family: str, seed: int) -> str:
    """The scene's name and file stem: ``"<family>-<seed>"``."""
    return f"{family}-{seed}"


def _check_input(family: str, seed: int) -> None:
    if family not in _BUILDERS:
        raise GenerateError(f"family {family!r}: unknown; expected one of {', '.join(FAMILIES)}")
    if (
        isinstance(seed, bool)
        or not isinstance(seed, int | np.integer)
        or not 0 <= seed <= MAX_SEED
    ):
        raise GenerateError(f"seed {seed!r}: expected an integer in 0 ... 2**63 - 1")


def _rng(seed: int, attempt: int) -> np.random.Generator:
    if attempt == 0:
        return np.random.Generator(np.random.PCG64(seed))
    return np.random.Generator(np.random.PCG64(np.random.SeedSequence([seed, attempt])))


def _draw_text(family: str, seed: int, attempt: int) -> str:
    table, notes = _BUILDERS[family](common.Draw(_rng(seed, attempt)))
    name = scene_name(family, seed)
    scene = {
        "name": name,
        "description": f"Generated {family} scene, seed {seed} (omnisim generate).",
        "frames": common.FRAMES,
        "frame_interval": common.FRAME_INTERVAL,
        **table,
    }
    header = [
        f"Generated scene: family {family}, seed {seed}, generator version "
        f"{GENERATOR_VERSION} (draw attempt {attempt}).",
        f"Regenerate: omnisim generate --family {family} --seed {seed} --out {name}.toml",
        "",
        *notes,
    ]
    return to_toml(scene, header)


def _loads(text: str, where: Path) -> str | None:
    """None if the loader accepts ``text``, else its one-line refusal."""
    # the loader needs trimesh (the sim extra): imported here so that importing this
    # package (FAMILIES, the omnisim command line) works without it
    from omnisim.scene import SceneError, load_scene

    where.write_text(text, encoding="utf-8")
    try:
        load_scene(where)
    except SceneError as exc:
        return str(exc)
    return None


def generate_scene(family: str, seed: int) -> str:
    """The TOML text of scene ``seed`` of ``family``; the same bytes on every call.

    Raises :class:`GenerateError` for an unknown family or a seed outside 0 ... 2**63 - 1,
    or when no draw in :data:`MAX_ATTEMPTS` loads (the last refusal is in the message).
    """
    _check_input(family, seed)
    refusal = None
    with tempfile.TemporaryDirectory(prefix="omnisim-generate-") as tmp:
        probe = Path(tmp) / f"{scene_name(family, seed)}.toml"
        for attempt in range(MAX_ATTEMPTS):
            text = _draw_text(family, seed, attempt)
            refusal = _loads(text, probe)
            if refusal is None:
                return text
    raise GenerateError(
        f"family {family!r}, seed {seed}: no loadable scene in {MAX_ATTEMPTS} draws; "
        f"last refusal: {refusal}"
    )


#: The first line of every generated scene file: the proof that a file is ours to replace.
MARK = "# Generated scene:"


def _refuse_foreign(path: Path) -> None:
    """GenerateError unless ``path`` is free or a scene this generator wrote (:data:`MARK`)."""
    if path.exists() or path.is_symlink():
        try:
            with open(path, encoding="utf-8", errors="replace") as fh:
                ours = path.is_file() and not path.is_symlink() and fh.readline().startswith(MARK)
        except OSError:
            ours = False
        if not ours:
            raise GenerateError(f"{path}: exists and is not a scene omnisim generate wrote (its "
                                f"first line is not '{MARK} ...'); nothing was replaced: choose "
                                "another --out or remove the file")  # fmt: skip


def write_scene(family: str, seed: int, path: str | Path) -> Path:
    """Generate and write the scene to ``path`` (atomically: a temporary name, then rename;
    the folder is created if missing). A file already there is replaced only when it is
    a generated scene (its first line is :data:`MARK`); anything else is a GenerateError,
    the file untouched."""
    text = generate_scene(family, seed)
    path = Path(path)
    _refuse_foreign(path)
    path.parent.mkdir(parents=True, exist_ok=True)
    fd, tmp = tempfile.mkstemp(prefix=f".{path.name}.", suffix=".tmp", dir=path.parent)
    try:
        with os.fdopen(fd, "w", encoding="utf-8") as fh:
            fh.write(text)
        os.replace(tmp, path)
    except BaseException:
        Path(tmp).unlink(missing_ok=True)
        raise
    return path


def generate_batch(family: str, seeds: Iterable[int], out_dir: str | Path) -> list[Path]:
    """Write ``<family>-<seed>.toml`` for every seed into ``out_dir`` (created if missing)."""
    seeds = list(seeds)
    for seed in seeds:
        _check_input(family, seed)
    out = Path(out_dir)
    for s in seeds:  # every target checked before the first is written
        _refuse_foreign(out / f"{scene_name(family, s)}.toml")
    out.mkdir(parents=True, exist_ok=True)
    return [write_scene(family, s, out / f"{scene_name(family, s)}.toml") for s in seeds]
