"""``python -m worker [--queues train,render,outputs] [--concurrency N]``: the same as ``voxnerf worker``;
``--exit-with-parent PID`` (what ``voxnerf serve`` passes) stops it when that process dies, SIGKILL included."""

from __future__ import annotations

import argparse

from worker.parent_watch import exit_with_parent
from worker.run import run_worker


def main() -> None:
    parser = argparse.ArgumentParser(prog="python -m worker", description=__doc__.splitlines()[0])
    parser.add_argument("--queues", default="train,render,outputs", help="comma-separated: train, render, outputs")
    parser.add_argument("--concurrency", type=int, default=1, help="worker processes")
    parser.add_argument("--exit-with-parent", type=int, metavar="PID",
                        help="stop when process PID (this one's parent) dies: warm shutdown, then SIGKILL")
    parser.add_argument("--stop-grace-s", type=float, default=15.0,
                        help="with --exit-with-parent: seconds the warm shutdown may take")
    args = parser.parse_args()
    if args.exit_with_parent is not None:
        exit_with_parent(args.exit_with_parent, args.stop_grace_s)
    run_worker([q for q in args.queues.split(",") if q], args.concurrency)


if __name__ == "__main__":
    main()
