"""``python -m worker [--queues train,render,outputs] [--concurrency N]``: the same as ``voxnerf worker``."""

from __future__ import annotations

import argparse

from worker.run import run_worker


def main() -> None:
    parser = argparse.ArgumentParser(prog="python -m worker", description=__doc__.splitlines()[0])
    parser.add_argument("--queues", default="train,render,outputs", help="comma-separated: train, render, outputs")
    parser.add_argument("--concurrency", type=int, default=1, help="worker processes")
    args = parser.parse_args()
    run_worker([q for q in args.queues.split(",") if q], args.concurrency)


if __name__ == "__main__":
    main()
