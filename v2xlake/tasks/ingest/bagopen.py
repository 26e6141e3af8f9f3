"""Open one agent's bag (ROS 2 sqlite3 / MCAP directory, or a ROS 1 ``.bag``) with rosbags.

Everything the reader needs comes from ``clip.yaml``: the bag path (absolute, or relative to
the clip folder) and the ``.msg`` files of custom types (a vendor INS). Types are resolved in
this order: definitions embedded in the bag (MCAP, ROS 1), then the ROS 2 standard store plus
the clip's custom definitions. Every failure becomes a ``ClipError`` naming the file, and
where it applies the topic, because the reader of a quarantine report must know where to look.

Recovery, documented: a ROS 2 ``metadata.yaml`` whose ``storage_identifier`` is empty (seen in
real recordings, e.g. the nebula Hesai QT128 test bag) is read as sqlite3 when every file it
lists is an SQLite database (checked by the file's magic header), or as MCAP when every file
starts with the MCAP magic. The original folder is left untouched: the reader is pointed at a
temporary shadow folder holding a patched ``metadata.yaml`` and symlinks to the data files.
``IngestConfig.recover_empty_storage_id=False`` turns the recovery off and raises instead.
"""

from __future__ import annotations

import os
import tempfile
from collections.abc import Iterator
from contextlib import contextmanager
from pathlib import Path
from typing import Any

import yaml
from rosbags.highlevel import AnyReader
from rosbags.interfaces import Connection, Nodetype
from rosbags.typesys import Stores, get_types_from_msg, get_typestore
from rosbags.typesys.store import Typestore

from v2xlake.schemas.clip import AgentConfig, ClipConfig
from v2xlake.schemas.errors import ClipError

SQLITE_MAGIC = b"SQLite format 3\x00"
MCAP_MAGIC = b"\x89MCAP0\r\n"
STAGE = "ingest"


def resolve(clip_dir: Path, rel: str) -> Path:
    """A path named in clip.yaml: absolute, or relative to the clip folder."""
    p = Path(rel).expanduser()
    return p if p.is_absolute() else (clip_dir / p).resolve()


def msg_type_name(path: Path) -> str:
    """``.../<package>/msg/<Name>.msg`` -> ``<package>/msg/<Name>`` (the ROS 2 convention)."""
    if path.parent.name != "msg" or not path.parent.parent.name:
        raise ValueError(f"message definition {path} is not laid out as <package>/msg/<Name>.msg")
    return f"{path.parent.parent.name}/msg/{path.stem}"


def build_typestore(clip_dir: Path, cfg: ClipConfig) -> Typestore:
    """ROS 2 standard types plus the clip's custom ``.msg`` definitions."""
    store = get_typestore(Stores.ROS2_HUMBLE)
    for rel in cfg.message_definitions:
        path = resolve(clip_dir, rel)
        if not path.is_file():
            raise ClipError(cfg.clip_id, "message definition file named in clip.yaml is missing",
                            path=str(path), stage=STAGE)
        try:
            store.register(get_types_from_msg(path.read_text(), msg_type_name(path)))
        except Exception as e:  # rosbags raises several types for bad definitions
            raise ClipError(cfg.clip_id, f"cannot parse message definition: {e}",
                            path=str(path), stage=STAGE) from e
    return store


def _detect_storage(bag_dir: Path, files: list[str]) -> str | None:
    kinds = set()
    for name in files:
        try:
            with (bag_dir / name).open("rb") as f:
                head = f.read(16)
        except OSError:
            return None
        kinds.add("sqlite3" if head.startswith(SQLITE_MAGIC)
                  else "mcap" if head.startswith(MCAP_MAGIC) else None)
    return kinds.pop() if len(kinds) == 1 else None


def _shadow_for_empty_storage(clip_id: str, agent_id: str, bag_dir: Path, recover: bool,
                              tmp: Path) -> Path:
    """Return the folder to open: ``bag_dir`` itself, or a patched shadow copy (see module doc)."""
    meta_path = bag_dir / "metadata.yaml"
    try:
        meta = yaml.safe_load(meta_path.read_text())
        info = meta["rosbag2_bagfile_information"]
    except Exception as e:
        raise ClipError(clip_id, f"unreadable rosbag2 metadata: {e}", agent_id=agent_id,
                        path=str(meta_path), stage=STAGE) from e
    files = [str(f) for f in (info.get("relative_file_paths") or [])]
    missing = [f for f in files if not (bag_dir / f).is_file()]
    if missing:  # before any advice about other fields: that one is the real problem
        raise ClipError(clip_id, f"metadata.yaml lists data file(s) {missing} that are not in "
                        f"the bag folder {bag_dir}: the bag is incomplete (copy the missing "
                        "file(s), or remove them from relative_file_paths and files)",
                        agent_id=agent_id, path=str(meta_path), stage=STAGE)
    for entry in info.get("topics_with_message_count") or []:
        topic = (entry or {}).get("topic_metadata") or {}
        if not topic.get("serialization_format"):
            raise ClipError(clip_id, f"field 'serialization_format' of topic "
                            f"{str(topic.get('name'))[:200]!r} is empty in metadata.yaml "
                            "(topics_with_message_count); ROS 2 bags use 'cdr': set it",
                            agent_id=agent_id, topic=str(topic.get("name") or "")[:200] or None,
                            path=str(meta_path), stage=STAGE)
    if info.get("storage_identifier"):
        return bag_dir
    kind = _detect_storage(bag_dir, files) if files else None
    if not recover or kind is None:
        why = ("recovery disabled" if not recover else
               f"cannot infer it: files {files} are not all SQLite or all MCAP")
        raise ClipError(clip_id, f"field 'storage_identifier' is empty in metadata.yaml ({why}); "
                        "set it to 'sqlite3' or 'mcap'", agent_id=agent_id,
                        path=str(meta_path), stage=STAGE)
    info["storage_identifier"] = kind
    shadow = tmp / bag_dir.name
    shadow.mkdir()
    (shadow / "metadata.yaml").write_text(yaml.safe_dump(meta, sort_keys=False))
    for name in files:
        (shadow / name).parent.mkdir(parents=True, exist_ok=True)
        os.symlink((bag_dir / name).resolve(), shadow / name)
    return shadow


@contextmanager
def open_bag(clip_id: str, agent: AgentConfig, bag: Path, typestore: Typestore,
             *, recover_empty_storage_id: bool = True,
             notes: list[str] | None = None) -> Iterator[AnyReader]:
    """Open ``bag`` as an ``AnyReader`` whose typestore knows every type we may decode."""
    if not bag.exists():
        raise ClipError(clip_id, "bag named in clip.yaml does not exist", agent_id=agent.agent_id,
                        path=str(bag), stage=STAGE)
    with tempfile.TemporaryDirectory(prefix="v2xlake-bag-") as tmp:
        path = bag
        if bag.is_dir():
            path = _shadow_for_empty_storage(clip_id, agent.agent_id, bag,
                                             recover_empty_storage_id, Path(tmp))
            if path != bag and notes is not None:
                notes.append(f"agent {agent.agent_id}: {bag}/metadata.yaml has an empty "
                             "storage_identifier; read as detected from the data files")
        try:
            reader = AnyReader([path], default_typestore=typestore)
            reader.open()
        except Exception as e:
            raise ClipError(clip_id, f"cannot open bag: {e}", agent_id=agent.agent_id,
                            path=str(bag), stage=STAGE) from e
        try:
            _complete_types(reader, typestore)
            yield reader
        finally:
            reader.close()


def _complete_types(reader: AnyReader, typestore: Typestore) -> None:
    """Bags with embedded definitions (MCAP, ROS 1) make rosbags ignore the default store;
    add the standard / custom types their connections lack, with their dependencies (never
    overriding the bag's own definitions, and never registering the whole store: building
    hundreds of classes would cost more than reading a small bag)."""
    have = reader.typestore.fielddefs
    mine = typestore.fielddefs
    missing: dict[str, Any] = {}

    def visit(name: str) -> None:
        if name in have or name in missing or name not in mine:
            return
        missing[name] = mine[name]
        for _fname, desc in mine[name][1]:
            _walk(desc)

    def _walk(desc: Any) -> None:
        kind, payload = desc
        if kind == Nodetype.NAME:
            visit(payload)
        elif kind in (Nodetype.ARRAY, Nodetype.SEQUENCE):
            _walk(payload[0])

    for c in reader.connections:
        visit(c.msgtype)
    if missing:
        reader.typestore.register(missing)


def connections_by_topic(reader: AnyReader) -> dict[str, Connection]:
    return {c.topic: c for c in reader.connections}


def knows_type(reader: AnyReader, msgtype: str) -> bool:
    return msgtype in reader.typestore.fielddefs


def header_stamp_ns(msg: Any) -> int:
    """``header.stamp`` as int64 ns (ROS 2 sec/nanosec; rosbags maps ROS 1 time the same way)."""
    st = msg.header.stamp
    return int(st.sec) * 1_000_000_000 + int(st.nanosec)
