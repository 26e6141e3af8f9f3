"""A release's notes: the figures (objects per class, distance density per class, clips
per weather x lighting) and ``RELEASE.md``, from the statistics
``storage.releases.release_statistics`` reads. Pure: data in, bytes and text out."""

from __future__ import annotations

import io
from typing import Any

from v2xlake.tasks.release_split import SPLITS


def plots(stats: dict[str, Any]) -> dict[str, bytes]:
    """PNG bytes per path inside the release (``plots/...``); no timestamps in their
    metadata, so a rebuild of the same selection gives the same bytes."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt
    import numpy as np

    out: dict[str, bytes] = {}

    def save(fig: Any, name: str) -> None:
        buf = io.BytesIO()
        fig.tight_layout()
        # no timestamps in PNG metadata: a rebuild of the same selection gives the same bytes
        fig.savefig(buf, format="png", dpi=100, metadata={"Software": None})
        plt.close(fig)
        out[name] = buf.getvalue()

    objs = stats["objects"]
    fig, ax = plt.subplots(figsize=(6, 3.5))
    if objs:
        ax.barh([o["category"] for o in objs][::-1], [o["objects"] for o in objs][::-1])
    ax.set_xlabel("objects (distinct instances)")
    ax.set_title("Objects per class")
    save(fig, "plots/objects_per_class.png")

    d = stats["_distances"]
    cats = np.asarray(d["category"], dtype=object)
    dist = np.asarray(d["distance_m"], dtype=float)
    fig, ax = plt.subplots(figsize=(6, 3.5))
    if dist.size:
        bins = np.linspace(0.0, max(float(dist.max()), 1.0), 25)
        for c in sorted(set(cats.tolist())):
            ax.hist(dist[cats == c], bins=bins, density=True, histtype="step", label=str(c))  # type: ignore[arg-type]
        ax.legend(fontsize=7)
    ax.set_xlabel("distance from the agent's LiDAR [m]")
    ax.set_ylabel("density")
    ax.set_title("Distance density per class")
    save(fig, "plots/distance_density_per_class.png")

    cond = stats["conditions"]
    weathers = sorted({c["weather"] for c in cond})
    lightings = sorted({c["lighting"] for c in cond})
    grid = np.zeros((len(weathers), len(lightings)))
    for c in cond:
        grid[weathers.index(c["weather"]), lightings.index(c["lighting"])] = c["clips"]
    fig, ax = plt.subplots(figsize=(5, 3.5))
    ax.imshow(grid if grid.size else np.zeros((1, 1)), cmap="Blues")
    ax.set_xticks(range(len(lightings)), lightings)
    ax.set_yticks(range(len(weathers)), weathers)
    for i in range(len(weathers)):
        for j in range(len(lightings)):
            ax.text(j, i, str(int(grid[i, j])), ha="center", va="center")
    ax.set_title("Clips per weather x lighting")
    save(fig, "plots/clips_weather_lighting.png")
    return out


def notes(meta: dict[str, Any], stats: dict[str, Any], exports: list[dict[str, Any]]) -> str:
    """``RELEASE.md``: the selection, its splits, conditions, objects, figures, contents."""
    counts = meta["split_counts"]
    lines = [
        f"# Release {meta['name']}", "",
        f"Built {meta['created_utc']} from lake `{meta['lake']}`.", "",
        f"Selection: `SELECT clip_id FROM clips WHERE status = 'ok' AND ({meta['where']})`", "",
        f"{len(meta['clip_ids'])} clips (scenes); splits (seed {meta['seed']}, fractions "
        f"{'/'.join(str(f) for f in meta['fractions'])}): "
        + ", ".join(f"{s} {counts[s]}" for s in SPLITS), "",
        "| split | clips |", "|---|---|",
        *[f"| {s} | {', '.join(c for c, v in meta['splits'].items() if v == s) or '-'} |"
          for s in SPLITS], "",
        "## Conditions", "", "| weather | lighting | clips |", "|---|---|---|",
        *[f"| {c['weather']} | {c['lighting']} | {c['clips']} |" for c in stats["conditions"]],
        "", "| location | clips |", "|---|---|",
        *[f"| {c['location']} | {c['clips']} |" for c in stats["locations"]], "",
        "## Objects", "",
    ]
    if stats["objects"]:
        lines += ["| class | objects | boxes |", "|---|---|---|",
                  *[f"| {o['category']} | {o['objects']} | {o['boxes']} |"
                    for o in stats["objects"]]]
    else:
        lines.append(stats.get("objects_note", "no annotations"))
    lines += ["", "![objects per class](plots/objects_per_class.png)",
              "![distance density per class](plots/distance_density_per_class.png)",
              "![clips per weather x lighting](plots/clips_weather_lighting.png)", "",
              "## Contents", "", "| format | files |", "|---|---|",
              *[f"| {e['format']} | {e['files']} |" for e in exports], "",
              "Verify with `v2xlake release verify " + meta["name"] + "` (every file is listed "
              "with its SHA-256 in `SHA256SUMS` and `checksums.json`)."]
    return "\n".join(lines) + "\n"
