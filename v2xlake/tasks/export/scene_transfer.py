"""Scene-transfer frame pairs (CATS-V2V supplementary B.5, eq. 6).

Overcast clips are the reference domain. Their frames, sampled at 1 Hz, are matched against
every frame of each other condition at the same location by the normalised similarity of
edge maps, ``S = <E_r, E_t> / (|E_r| |E_t|)`` (eq. 6a), keeping the argmax (eq. 6b).

Edge maps are Canny edges (or Sobel magnitude) of the grayscale image, area-downsampled to
``edge_width`` pixels wide: the downsampling turns one-pixel edges into a soft density, so
frames a metre apart still overlap, which a raw Canny map (one pixel thick) would not.
The second-best score is kept next to the best one: a small margin is the thing a person
verifying the pairs (the paper verifies them by hand) should look at first.
"""

from __future__ import annotations

import csv
from collections import defaultdict
from collections.abc import Sequence
from dataclasses import dataclass
from pathlib import Path
from typing import Literal

import cv2
import numpy as np
import pyarrow as pa
from pydantic import BaseModel, ConfigDict, Field

from v2xlake.schemas.errors import ClipError
from v2xlake.schemas.stage import StageReport
from v2xlake.storage.files import write_parquet
from v2xlake.storage.lake import Lake
from v2xlake.tasks.export.common import file_output, report_step
from v2xlake.tasks.reader import load_clip


class SceneTransferConfig(BaseModel):
    model_config = ConfigDict(frozen=True, extra="forbid")

    camera: str = "CAM_FRONT"
    agents: list[str] | None = None  # None: the clip's reference agent only
    reference_weather: str = "overcast"
    sample_hz: float = Field(1.0, gt=0)
    edge: Literal["canny", "sobel"] = "canny"
    canny_thresholds: tuple[int, int] = (50, 150)
    edge_width: int = Field(80, ge=8, description="edge map width after area downsampling")
    candidate_stride: int = Field(1, ge=1)
    contact_sheet_rows: int = 12
    copy_images: bool = True


def edge_map(img_bgr: np.ndarray, cfg: SceneTransferConfig) -> np.ndarray:
    """Unit-norm flattened edge map (so eq. 6a becomes a dot product)."""
    g = cv2.cvtColor(img_bgr, cv2.COLOR_BGR2GRAY) if img_bgr.ndim == 3 else img_bgr
    g = cv2.GaussianBlur(g, (5, 5), 1.0)
    if cfg.edge == "canny":
        e: np.ndarray = cv2.Canny(g, *cfg.canny_thresholds).astype(np.float32)
    else:
        gx = cv2.Sobel(g, cv2.CV_32F, 1, 0, ksize=3)
        gy = cv2.Sobel(g, cv2.CV_32F, 0, 1, ksize=3)
        e = cv2.magnitude(gx, gy)
    h = max(1, round(cfg.edge_width * g.shape[0] / g.shape[1]))
    small = cv2.resize(e, (cfg.edge_width, h), interpolation=cv2.INTER_AREA).reshape(-1)
    n = float(np.linalg.norm(small))
    return small / n if n > 0 else small


def similarity(e_r: np.ndarray, e_t: np.ndarray) -> float:
    """Eq. 6a on raw (not yet normalised) edge maps."""
    a, b = e_r.reshape(-1).astype(np.float64), e_t.reshape(-1).astype(np.float64)
    d = float(np.linalg.norm(a) * np.linalg.norm(b))
    return float(a @ b / d) if d > 0 else 0.0


@dataclass
class _Frames:
    clip_id: str
    agent_id: str
    condition: str
    frame_idx: np.ndarray
    stamp_ns: np.ndarray
    blob: list[str]
    edges: np.ndarray  # (N, D) unit rows


def _decode(lake: Lake, key: str) -> np.ndarray:
    img = cv2.imdecode(np.frombuffer(lake.read_blob("clean", key), np.uint8), cv2.IMREAD_COLOR)
    if img is None:
        raise ValueError(f"cannot decode blob {key}")
    return img


def _load(lake: Lake, clip_id: str, cfg: SceneTransferConfig, reference: bool
          ) -> tuple[str, str, list[_Frames]]:
    clip = load_clip(lake, clip_id)
    cond = f"{clip.info.get('weather')}/{clip.info.get('lighting')}"
    out = []
    for aid in cfg.agents or [clip.reference_agent]:
        agent = clip.agents.get(aid)
        if agent is None or cfg.camera not in agent.cameras:
            continue
        fr = agent.cameras[cfg.camera]
        if reference:  # 1 Hz: the frame nearest each whole second of the relative axis
            t = fr.stamp_ns
            grid = np.arange(np.ceil(t[0] * cfg.sample_hz / 1e9),
                             np.floor(t[-1] * cfg.sample_hz / 1e9) + 1) * 1e9 / cfg.sample_hz
            sel = np.unique(np.abs(t[None, :] - grid[:, None]).argmin(1)) if len(grid) \
                else np.array([0])
        else:
            sel = np.arange(0, len(fr), cfg.candidate_stride)
        edges = np.stack([edge_map(_decode(lake, fr.blob[j]), cfg) for j in sel])
        out.append(_Frames(clip_id, aid, cond, fr.frame_idx[sel], fr.stamp_ns[sel],
                           [fr.blob[j] for j in sel], edges))
    return str(clip.info.get("location")), str(clip.info.get("weather")), out


def export_scene_transfer(lake: Lake, clip_ids: Sequence[str], out_dir: Path | str,
                          config: SceneTransferConfig = SceneTransferConfig()  # noqa: B008
                          ) -> StageReport:
    cfg = config
    out = Path(out_dir)
    out.mkdir(parents=True, exist_ok=True)
    by_loc: dict[str, dict[str, list[_Frames]]] = defaultdict(lambda: defaultdict(list))
    refs: dict[str, list[_Frames]] = defaultdict(list)
    for n_loaded, cid in enumerate(clip_ids, start=1):
        clip_info = load_clip(lake, cid).info
        is_ref = str(clip_info.get("weather")) == cfg.reference_weather
        loc, _, frames = _load(lake, cid, cfg, is_ref)
        for f in frames:
            (refs[loc] if is_ref else by_loc[loc][f.condition]).append(f)
        report_step("scene-transfer: clips' edge maps", n_loaded, len(clip_ids))
    rows: list[dict[str, object]] = []
    for loc, ref_list in refs.items():
        for cond, cands in by_loc.get(loc, {}).items():
            C = np.concatenate([c.edges for c in cands])
            owner = np.concatenate([np.full(len(c.edges), i) for i, c in enumerate(cands)])
            pos = np.concatenate([np.arange(len(c.edges)) for c in cands])
            for r in ref_list:
                S = r.edges @ C.T  # eq. 6a, rows already unit norm
                for k in range(len(r.edges)):
                    order = np.argsort(S[k])[::-1]
                    best = int(order[0])
                    c = cands[int(owner[best])]
                    j = int(pos[best])
                    rows.append(dict(
                        location=loc, condition=cond, ref_clip=r.clip_id, ref_agent=r.agent_id,
                        ref_frame_idx=int(r.frame_idx[k]), ref_t_ns=int(r.stamp_ns[k]),
                        ref_blob=r.blob[k], match_clip=c.clip_id, match_agent=c.agent_id,
                        match_frame_idx=int(c.frame_idx[j]), match_t_ns=int(c.stamp_ns[j]),
                        match_blob=c.blob[j], score=float(S[k, best]),
                        second_score=float(S[k, order[1]]) if len(order) > 1 else float("nan"),
                        camera=cfg.camera))
    if not refs:
        raise ClipError(",".join(clip_ids), f"no {cfg.reference_weather!r} clip among the "
                        "selection: nothing to use as the reference domain",
                        stage="export_scene_transfer")
    report = StageReport(stage="export_scene_transfer", clip_id=",".join(clip_ids))
    table = pa.Table.from_pylist(rows) if rows else \
        pa.table({"location": pa.array([], pa.string())})
    write_parquet(out / "pairs.parquet", table, compression="snappy")
    with open(out / "pairs.csv", "w", newline="") as fh:
        if rows:
            w = csv.DictWriter(fh, fieldnames=list(rows[0]))
            w.writeheader()
            w.writerows(rows)
    report.outputs += [file_output(out / "pairs.parquet", len(rows)),
                       file_output(out / "pairs.csv", len(rows))]
    if cfg.copy_images:
        for n_copied, r_ in enumerate(rows, start=1):
            d = out / "pairs" / str(r_["location"]) / f"{r_['ref_clip']}_{r_['ref_agent']}_" \
                f"{int(r_['ref_frame_idx']):06d}"  # type: ignore[call-overload]
            d.mkdir(parents=True, exist_ok=True)
            (d / "reference.png").write_bytes(lake.read_blob("clean", str(r_["ref_blob"])))
            (d / f"{str(r_['condition']).replace('/', '_')}.png").write_bytes(
                lake.read_blob("clean", str(r_["match_blob"])))
            report_step("scene-transfer: image pairs copied", n_copied, len(rows))
    if rows:
        sheet = _contact_sheet(lake, rows[:cfg.contact_sheet_rows])
        cv2.imwrite(str(out / "contact_sheet.png"), sheet)
        report.images.append(str(out / "contact_sheet.png"))
        sc = np.array([float(r_["score"]) for r_ in rows])  # type: ignore[arg-type]
        report.metrics = {"pairs": float(len(rows)), "score_mean": float(sc.mean()),
                          "score_min": float(sc.min())}
    else:
        report.notes.append("no candidate clip under another condition at a reference "
                            "location")
    return report


def _contact_sheet(lake: Lake, rows: list[dict[str, object]], width: int = 320) -> np.ndarray:
    lines = []
    for r in rows:
        a = _decode(lake, str(r["ref_blob"]))
        b = _decode(lake, str(r["match_blob"]))
        h = round(a.shape[0] * width / a.shape[1])
        a, b = cv2.resize(a, (width, h)), cv2.resize(b, (width, h))
        for img, txt in ((a, f"{r['ref_clip']} #{r['ref_frame_idx']} (reference)"),
                         (b, f"{r['condition']} {r['match_clip']} #{r['match_frame_idx']} "
                             f"S={float(r['score']):.3f}")):  # type: ignore[arg-type]
            cv2.putText(img, txt, (4, 14), cv2.FONT_HERSHEY_SIMPLEX, 0.4, (0, 255, 255), 1,
                        cv2.LINE_AA)
        lines.append(np.hstack([a, b]))
    return np.vstack(lines)
