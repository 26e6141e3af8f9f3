"""A trivial Prefect flow (no tests here): the anchor the no-op benchmark compares a v2xlake
call with, and a flow whose run page the UI test opens. ``trivial_clip_flow`` has the shape
of ``process-clip``: seven tasks in a row, each returning at once."""

from __future__ import annotations

from prefect import flow, task


@task
def noop_task(i: int) -> int:
    return i


@flow(name="trivial")
def trivial_flow(n: int = 1) -> int:
    return n


@flow(name="trivial-clip")
def trivial_clip_flow(n_tasks: int = 7) -> int:
    return sum(noop_task.submit(i).result() for i in range(n_tasks))


if __name__ == "__main__":
    import sys

    from prefect.context import get_run_context  # noqa: F401

    state = trivial_flow(int(sys.argv[1]) if len(sys.argv) > 1 else 1, return_state=True)
    print(f"flow_run_id={state.state_details.flow_run_id}", flush=True)
