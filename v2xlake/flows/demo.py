"""``v2xlake demo``: what a newcomer should see in a few minutes on a laptop.

Simulates a small two-vehicle clip, runs every available stage through Prefect (temporary
local server), then prints a per-stage table, where the lake and the pictures are, and
three example SQL queries with their answers.
"""

from __future__ import annotations

import time
from pathlib import Path

EXAMPLE_QUERIES: tuple[tuple[str, str], ...] = (
    ("LiDAR points per agent",
     "SELECT agent_id, count(*) AS points, count(DISTINCT frame_idx) AS frames "
     "FROM lidar_points GROUP BY agent_id ORDER BY agent_id"),
    ("Registration quality (eq. 1a -> 1b refinement per frame pair)",
     "SELECT agent_ref, agent_other, count(*) AS frames, round(avg(fitness), 3) AS fitness, "
     "round(avg(inlier_rmse), 3) AS rmse_m, round(avg(correction_m), 3) AS correction_m, "
     "sum(CASE WHEN accepted THEN 1 ELSE 0 END) AS accepted "
     "FROM registrations GROUP BY ALL ORDER BY ALL"),
    ("QA checks (failures first)",
     "SELECT severity, passed, count(*) AS checks, "
     "string_agg(DISTINCT CASE WHEN NOT passed THEN \"check\" END, ', ') AS failed_checks "
     "FROM qa_checks GROUP BY ALL ORDER BY passed, severity"),
)


def run_demo(out: Path, *, seconds: float = 2.0, cameras: int = 2, seed: int = 7,
             storage: str = "sqlite3") -> int:
    from rich.console import Console
    from rich.panel import Panel

    from v2xlake.flows.bookkeeping import query
    from v2xlake.flows.cli import print_arrow, run_process, sim_config, stage_table
    from v2xlake.storage.lake import Lake

    console = Console(highlight=False)
    out = Path(out).resolve()
    lake_dir = out / "lake"
    t_all = time.perf_counter()
    console.print(Panel.fit(
        "v2xlake demo: simulate a two-vehicle clip, then ingest -> qa -> anonymize -> deskew "
        "-> register -> annotate -> align,\neach stage a Prefect task in a per-clip flow, "
        f"results in a Parquet lake under {lake_dir}", title="v2xlake"))

    cfg = sim_config("small", seconds, storage, seed, "red,black", str(cameras),
                     clip_id=f"demo_s{seed}")
    clip_dir = out / "clips" / str(cfg.name)
    t0 = time.perf_counter()
    if (clip_dir / "clip.yaml").exists():
        console.print(f"[1/3] clip already simulated: {clip_dir}")
    else:
        from v2xlake.tasks.simulate import simulate

        with console.status(f"[1/3] simulating {seconds:g} s, agents red+black, "
                            f"{cameras} camera(s) each ..."):
            simulate(clip_dir, cfg)
        console.print(f"[1/3] simulated clip {cfg.name} in {time.perf_counter() - t0:.1f} s"
                      f" -> {clip_dir}")

    console.print("[2/3] processing through Prefect (a temporary local server starts first)")
    t1 = time.perf_counter()
    results = run_process([str(clip_dir)], str(lake_dir), console=console)
    t_proc = time.perf_counter() - t1
    summary = results[0]
    console.print(stage_table(summary))
    if summary["status"] != "ok":
        console.print(f"[red]clip {summary['clip_id']} {summary['status']}:[/] "
                      f"{summary.get('error')}")
        if summary.get("quarantine_report"):
            console.print(f"quarantine report: {summary['quarantine_report']}")

    pictures: list[str] = [img for o in summary["stages"]
                           for img in (o.get("report") or {}).get("images", [])]
    console.print(f"\nlake:      {lake_dir}")
    console.print(f"catalog:   {lake_dir / 'catalog.duckdb'}  (v2xlake query \"SQL\" "
                  f"--lake {lake_dir})")
    console.print(f"manifests: {lake_dir / 'manifests' / summary['clip_id']}")
    if pictures:
        console.print("pictures:")
        for p in pictures:
            console.print(f"  {p}")

    console.print("\n[3/3] example queries")
    lake = Lake(str(lake_dir))
    for title, sql in EXAMPLE_QUERIES:
        console.print(f"\n[bold]{title}[/]\n[dim]{sql}[/]")
        try:
            print_arrow(query(lake, sql), "table", console)
        except Exception as exc:
            first = str(exc).splitlines()[0] if str(exc) else type(exc).__name__
            console.print(f"[yellow](not available: {first})[/]")
    console.print(f"\ndemo finished in {time.perf_counter() - t_all:.1f} s "
                  f"(processing {t_proc:.1f} s)")
    return 0 if summary["status"] == "ok" else 1

