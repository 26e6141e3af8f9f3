"""The clip folder as delivered: its ``clip.yaml`` read and explained when invalid, the input
files it names (for the manifest), and the rule that nothing outside the folder (or an
operator-allowed root) is read or copied. Files only: no lake."""

from __future__ import annotations

import functools
import os
import re
from collections.abc import Sequence
from pathlib import Path
from typing import Any

import yaml
from pydantic import BaseModel, ValidationError

from v2xlake.schemas.clip import ID_PATTERN, ClipConfig, load_yaml
from v2xlake.schemas.errors import ClipError
from v2xlake.tasks.ingest.bagopen import STAGE, resolve


def load_clip_config(clip_dir: Path) -> ClipConfig:
    path = clip_dir / "clip.yaml"
    if not path.is_file():
        raise ClipError(clip_dir.name, "clip folder has no clip.yaml", path=str(path), stage=STAGE)
    try:
        text = path.read_text()
        return _parsed_clip_config(text).model_copy(deep=True)
    except (yaml.YAMLError, OSError, UnicodeDecodeError) as e:
        raise ClipError(clip_dir.name, f"clip.yaml is not readable YAML: {e}", path=str(path),
                        stage=STAGE) from e
    except ValidationError as e:
        data = load_yaml(text)
        cid, agent, reason = explain_invalid(data, e)
        # not chained: a pydantic error renders its input, and whatever formats the
        # traceback (Prefect's log handler) would render all of it
        raise ClipError(cid or clip_dir.name, f"invalid clip.yaml: {reason}", agent_id=agent,
                        path=str(path), stage=STAGE) from None
    except ValueError as e:
        raise ClipError(clip_dir.name, f"invalid clip.yaml: {e}", path=str(path),
                        stage=STAGE) from e


@functools.lru_cache(maxsize=64)
def _parsed_clip_config(text: str) -> ClipConfig:
    """Parsed and validated once per distinct text: every no-op check of a clip reads its
    clip.yaml, and parsing a large one is most of the check's cost (callers get a copy)."""
    return ClipConfig.model_validate(load_yaml(text))


def explain_invalid(data: Any, e: ValidationError) -> tuple[str | None, str | None, str]:
    """(clip id, agent id, reason) of a clip.yaml that does not validate: each problem with
    its place written as keys (``agents[red].sensors[LIDAR_TOP].extrinsics``), an unknown
    key named with the closest known one."""
    import difflib

    cid = data.get("clip_id") if isinstance(data, dict) else None
    cid = cid if isinstance(cid, str) and re.fullmatch(ID_PATTERN, cid) else None
    agents: set[str] = set()
    parts = []
    for err in e.errors():
        loc, node, where = err["loc"], data, []
        for i, key in enumerate(loc):
            if isinstance(key, int) and isinstance(node, list) and key < len(node):
                node = node[key]
                named = node.get("agent_id") or node.get("name") if isinstance(node, dict) \
                    else None
                where.append(f"[{named}]" if isinstance(named, str) else f"[{key}]")
                if i > 0 and loc[i - 1] == "agents" and isinstance(named, str):
                    agents.add(named)
            elif isinstance(node, dict) and key in node and not (
                    err["type"] == "extra_forbidden" and i == len(loc) - 1):
                node = node[key]
                where.append(f".{key}")
            else:
                continue  # a union member's tag (pose kinds), or the unknown key itself
        place = "".join(where).lstrip(".") or "(top level)"
        if err["type"] == "extra_forbidden":
            key = str(loc[-1])
            known = _known_keys(loc, data)
            near = difflib.get_close_matches(key, known, n=1)
            hint = f" (did you mean {near[0]!r}?)" if near else (
                f" (known keys: {', '.join(sorted(known))})" if known else "")
            parts.append(f"{place}: unknown key {key!r}{hint}")
        elif err["type"] == "missing":
            parts.append(f"{place}: missing key {str(loc[-1])!r}")
        else:
            parts.append(f"{place}: {err['msg']}")
    agent = next(iter(agents)) if len(agents) == 1 else None
    return cid, agent, "; ".join(parts)


def _known_keys(loc: tuple[Any, ...], data: Any) -> list[str]:
    """The keys the model at ``loc[:-1]`` accepts (for a 'did you mean')."""
    from v2xlake.schemas import clip as clipschema

    model: Any = ClipConfig
    for key in loc[:-1]:
        if isinstance(key, int) or model is None:
            continue
        fields = getattr(model, "model_fields", {})
        if key in fields:
            model = _model_of(fields[key].annotation)
        else:  # a union tag, e.g. the pose kind 'odometry'
            model = next((m for m in vars(clipschema).values() if isinstance(m, type)
                          and issubclass(m, BaseModel) and "kind" in m.model_fields
                          and m.model_fields["kind"].default == key), None)
    return list(getattr(model, "model_fields", {}))


def _model_of(annotation: Any) -> Any:
    """The pydantic model inside ``X | None`` / ``list[X]`` (None for plain values)."""
    import typing

    if isinstance(annotation, type) and issubclass(annotation, BaseModel):
        return annotation
    for arg in typing.get_args(annotation):
        m = _model_of(arg)
        if m is not None:
            return m
    return None


def bag_files(bag: Path) -> list[Path]:
    if bag.is_dir():
        return sorted(p for p in bag.rglob("*") if p.is_file() and not p.name.startswith("."))
    return [bag]


def clip_inputs(clip_dir: str | Path) -> tuple[str, list[Path]]:
    """The clip id and every input file of the ingest stage (clip.yaml, bags, message
    definitions, annotation file) so the flow can hash them for the manifest before running."""
    d = Path(clip_dir).resolve()
    cfg = load_clip_config(d)
    files = [d / "clip.yaml"]
    for a in cfg.agents:
        files.extend(bag_files(resolve(d, a.bag)))
    files.extend(resolve(d, m) for m in cfg.message_definitions)
    if cfg.annotations:
        files.append(resolve(d, cfg.annotations))
    return cfg.clip_id, [f for f in files if f.exists()]


def check_inputs(clip_dir: Path, cfg: ClipConfig, allowed_roots: Sequence[str] = ()) -> None:
    """Every file clip.yaml names must exist and resolve (after symlinks) inside the clip
    folder or an operator-allowed root: a clip folder is untrusted input, and nothing
    outside it may be read, linked or copied into the lake because a clip.yaml says so."""
    roots = delivery_roots(clip_dir, allowed_roots)
    named: list[tuple[str | None, str, str]] = [(a.agent_id, "bag", a.bag) for a in cfg.agents]
    named += [(None, "message definition", m) for m in cfg.message_definitions]
    if cfg.annotations:
        named.append((None, "annotation file", cfg.annotations))
    for agent_id, what, rel in named:
        p = resolve(clip_dir, rel)
        real = os.path.realpath(p)
        if not is_inside(real, roots):
            raise ClipError(cfg.clip_id, f"{what} {rel!r} resolves to {real}, outside the clip "
                            "folder (an operator may allow a root: ingest.allowed_bag_roots)",
                            agent_id=agent_id, path=str(p), stage=STAGE)
        if not p.exists():
            raise ClipError(cfg.clip_id, f"{what} named in clip.yaml does not exist",
                            agent_id=agent_id, path=str(p), stage=STAGE)


def delivery_roots(clip_dir: Path, allowed_roots: Sequence[str]) -> list[str]:
    """Where a delivery's files may resolve to: the clip folder and operator-allowed roots."""
    return [os.path.realpath(clip_dir), *(os.path.realpath(r) for r in allowed_roots)]


def is_inside(real: str, roots: Sequence[str]) -> bool:
    return any(os.path.commonpath([r, real]) == r for r in roots)


def plain_files(top: Path, roots: Sequence[str], clip_id: str, *,
                skip_top: frozenset[str] = frozenset(), agent_id: str | None = None
                ) -> list[tuple[str, str]]:
    """``(relative path, real path)`` of every visible regular file under ``top``, for the
    landing copy, which must hold plain files only: ``v2xlake query`` may read the lake's
    folders, and a symlink copied (or hard-linked: ``link()`` links the symlink itself) into
    the lake would let it read whatever the link points at.

    A symlink in a delivery is untrusted like a path in clip.yaml, so the same rule as
    ``check_inputs``: a file symlink that resolves inside ``roots`` (the clip folder, an
    operator-allowed root) is taken as the file it points at; one that resolves elsewhere
    is refused with a ``ClipError`` even when clip.yaml does not name it (a delivery has no
    business pointing outside itself, and skipping it silently would hide the attempt).
    A symlinked folder is never walked: pointing outside ``roots`` it is refused the same
    way; inside, it is the same files again (a bag clip.yaml names through it is resolved
    and copied as an external bag). Hidden names, ``skip_top`` entries at the top level,
    dangling links and non-regular files (FIFOs, sockets, devices) are left out."""
    out: list[tuple[str, str]] = []
    todo: list[Path] = [top]
    while todo:
        folder = todo.pop()
        try:
            entries = sorted(os.scandir(folder), key=lambda e: e.name)
        except OSError as e:
            raise ClipError(clip_id, f"cannot list {folder}: {e.strerror}", agent_id=agent_id,
                            path=str(folder), stage=STAGE) from e
        for entry in entries:
            path = Path(entry.path)
            rel = path.relative_to(top).as_posix()
            if entry.name.startswith(".") or (folder == top and entry.name in skip_top):
                continue
            if entry.is_symlink():
                real = os.path.realpath(path)
                if not is_inside(real, roots):
                    raise ClipError(
                        clip_id, f"{rel!r} is a symlink to {real}, outside the clip folder: "
                        "refused (the landing copy holds the delivery's own files only; an "
                        "operator may allow a root: ingest.allowed_bag_roots)",
                        agent_id=agent_id, path=str(path), stage=STAGE)
                if os.path.isfile(real):
                    out.append((rel, real))
            elif entry.is_dir(follow_symlinks=False):
                todo.append(path)
            elif entry.is_file(follow_symlinks=False):
                out.append((rel, entry.path))
    return sorted(out)
