"""``v2xlake view CLIP``: look at a processed clip at once.

Two outputs, both from the clean zone:

* a PNG of one cooperative sample: bird's-eye view of every agent's deskewed points in the
  clip's world frame (one colour per agent), the annotated boxes (outlined, labelled with
  their global instance id), each agent's position and heading, and each agent's camera
  images at that time beside it;
* an MCAP file that Foxglove opens as it is: every agent on one timeline (the clip's relative
  time), deskewed clouds, /tf from the poses, boxes as markers, images and calibration (the
  rosbag export with ``combine_agents``; open ``<clip>_all/<clip>_all.mcap``, set the 3D
  panel's display frame to ``map``).
"""

from __future__ import annotations

from pathlib import Path

import numpy as np
from pydantic import BaseModel, ConfigDict, Field

from v2xlake.schemas.errors import ClipError
from v2xlake.storage.lake import Lake
from v2xlake.storage.reader import DESKEWED, read_point_frame
from v2xlake.tasks.export.common import report_step
from v2xlake.tasks.geometry import apply, box_corners, quat_wxyz_of
from v2xlake.tasks.reader import boxes_matrices, load_clip, match_agents, registered_T

AGENT_COLOURS = ("#e4572e", "#17bebb", "#76b041", "#ffc914", "#8e6c8a", "#2e86ab")


class ViewConfig(BaseModel):
    model_config = ConfigDict(frozen=True, extra="forbid")

    png: bool = True
    mcap: bool = True
    sample: int | None = Field(None, description="cooperative sample index (default: middle)")
    range_m: float = Field(45.0, gt=0, description="half width of the bird's-eye view")
    max_points: int = Field(60_000, gt=0, description="points drawn per agent (subsampled)")
    tolerance_ms: float = 50.0
    lidar_sensor: str = "LIDAR_TOP"


def render_png(lake: Lake, clip_id: str, out: Path, config: ViewConfig = ViewConfig()) -> Path:  # noqa: B008
    """One cooperative sample as a picture (see the module docstring)."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt
    from matplotlib.gridspec import GridSpec

    clip = load_clip(lake, clip_id)
    ref = clip.agents[clip.reference_agent]
    lf = ref.lidar[ref.lidar_sensor(config.lidar_sensor)]
    keep, nears = match_agents(clip, lf.points_t_ns, config.tolerance_ms * 1e6,
                               sensor=config.lidar_sensor)
    rows = np.flatnonzero(keep)
    if len(rows) == 0:
        raise ClipError(clip_id, "no LiDAR frame that every agent can provide (deskewed, "
                        "inside pose coverage)", stage="view")
    k = rows[len(rows) // 2] if config.sample is None else rows[config.sample]
    t_ref = int(lf.points_t_ns[k])
    T_wl_ref = ref.T_world_ego(t_ref, clip_id=clip_id)[0] @ \
        ref.sensors[ref.lidar_sensor(config.lidar_sensor)].T_ego_sensor
    cams = [(aid, ch) for aid, a in clip.agents.items() for ch in sorted(a.cameras)
            if ch in a.cameras_calib() and len(a.cameras[ch])]
    fig = plt.figure(figsize=(16 if cams else 10, 10), dpi=100)
    gs = GridSpec(max(len(cams), 1), 2 if cams else 1, figure=fig,
                  width_ratios=[1.25, 1] if cams else [1])
    ax = fig.add_subplot(gs[:, 0])
    ax.set_facecolor("#101418")
    centre = np.mean([a.T_world_ego(t_ref, clip_id=clip_id)[0][:2, 3]
                      for a in clip.agents.values() if a.poses.covers(t_ref)], axis=0)
    rng = np.random.default_rng(0)
    for n, (aid, agent) in enumerate(clip.agents.items()):
        colour = AGENT_COLOURS[n % len(AGENT_COLOURS)]
        sensor = agent.lidar_sensor(config.lidar_sensor)
        alf = agent.lidar[sensor]
        i = int(nears[aid][k])
        T = agent.T_world_ego(int(alf.points_t_ns[i]), clip_id=clip_id)[0] @ \
            agent.sensors[sensor].T_ego_sensor
        reg = registered_T(clip, aid, int(lf.frame_idx[k])) if aid != clip.reference_agent \
            else None
        if reg is not None:
            T = T_wl_ref @ reg
        fr = read_point_frame(lake, clip_id, aid, int(alf.frame_idx[i]), table=DESKEWED,
                              sensor=sensor)
        if fr is not None and len(fr.xyz):
            sel = fr.xyz if len(fr.xyz) <= config.max_points else \
                fr.xyz[rng.choice(len(fr.xyz), config.max_points, replace=False)]
            w = apply(T, sel.astype(np.float64))
            dot = float(np.clip(3e4 / len(sel), 0.3, 4.0))  # sparse clouds stay visible
            ax.scatter(w[:, 0], w[:, 1], s=dot, c=colour, alpha=0.7, linewidths=0,
                       label=f"{aid} ({len(fr.xyz):,} points, frame {fr.frame_idx})")
        ego = agent.T_world_ego(int(alf.points_t_ns[i]), clip_id=clip_id)[0]
        head = ego[:2, :2] @ np.array([3.0, 0.0])
        ax.arrow(ego[0, 3], ego[1, 3], head[0], head[1], width=0.5, color=colour, zorder=5)
        ann = agent.annotations
        if ann.num_rows:
            ann = ann.filter(np.asarray(ann["frame_idx"].to_numpy()) == int(alf.frame_idx[i]))
        if ann.num_rows:
            B = T @ boxes_matrices(ann)
            size = np.stack([ann[c].to_numpy() for c in "wlh"], 1)
            corners = box_corners(B[:, :3, 3], size, quat_wxyz_of(B))
            for b, iid in enumerate(ann["instance_id"].to_pylist()):
                c = corners[b, [0, 1, 2, 3, 0], :2]  # the bottom face, closed
                ax.plot(c[:, 0], c[:, 1], color=colour, lw=1.2, zorder=4)
                if n == 0 or iid not in ref.annotations["instance_id"].to_pylist():
                    ax.text(B[b, 0, 3], B[b, 1, 3], iid, color="white", fontsize=7,
                            ha="center", va="center", zorder=6)
    ax.set_xlim(centre[0] - config.range_m, centre[0] + config.range_m)
    ax.set_ylim(centre[1] - config.range_m, centre[1] + config.range_m)
    ax.set_aspect("equal")
    ax.set_xlabel("x (m, clip ENU)")
    ax.set_ylabel("y (m)")
    ax.set_title(f"{clip_id}: t = {t_ref / 1e9:.3f} s, reference frame {int(lf.frame_idx[k])}")
    leg = ax.legend(loc="upper right", fontsize=8)
    for h in leg.legend_handles:
        sizes = getattr(h, "set_sizes", None)
        if sizes is not None:
            sizes([30.0])
    for r, (aid, ch) in enumerate(cams):
        import cv2

        frames = clip.agents[aid].cameras[ch]
        j = int(np.argmin(np.abs(frames.stamp_ns - t_ref)))
        img = cv2.imdecode(np.frombuffer(lake.read_blob("clean", frames.blob[j]), np.uint8),
                           cv2.IMREAD_COLOR)
        cax = fig.add_subplot(gs[r, 1])
        if img is not None:
            cax.imshow(img[:, :, ::-1])
        cax.set_title(f"{aid} {ch} at {int(frames.stamp_ns[j]) / 1e9:.3f} s", fontsize=9)
        cax.axis("off")
    fig.tight_layout()
    out.parent.mkdir(parents=True, exist_ok=True)
    fig.savefig(out)
    plt.close(fig)
    return out


def view_clip(lake: Lake, clip_id: str, out_dir: Path | str,
              config: ViewConfig = ViewConfig()) -> list[Path]:  # noqa: B008
    """Write ``<out>/<clip>.png`` and/or ``<out>/<clip>_all/*.mcap``; returns their paths."""
    from v2xlake.tasks.export.rosbag import RosbagExportConfig, export_rosbag

    out = Path(out_dir)
    paths: list[Path] = []
    if config.png:
        paths.append(render_png(lake, clip_id, out / f"{clip_id}.png", config))
        report_step(f"view {clip_id}: picture", 1, 1)
    if config.mcap:
        rep = export_rosbag(lake, clip_id, None, out, config=RosbagExportConfig(
            storage="mcap", combine_agents=True, lidar_table=DESKEWED,
            lidar_sensor=config.lidar_sensor))
        paths += [Path(o.path) for o in rep.outputs if o.path.endswith(".mcap")]
    return paths
