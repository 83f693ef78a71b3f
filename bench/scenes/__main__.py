"""The randomized scene suite: the receiver over the range real cameras and screens span.

    python -m bench.scenes [--scenes 240] [--seed 0] [--jobs 2] [--out docs] [--targets-only]

Draws ``--scenes`` scenes of the suite of ``--seed`` (``bench.scenes.draw``), simulates each and
runs the streaming receiver on it (``bench.scenes.run``), then writes the per-scene results to
``<out>/results/scenes.json`` and the distributions (``bench.scenes.summary``) to its section of
``<out>/BENCHMARKS.md``; ``--targets-only`` runs just the scenes the issue's targets cover.
Scenes run ``--jobs`` at a time, with the same results for any number of jobs. Each scene's
result is printed as it completes, and ``--resume`` takes those of an
earlier run's output; ``--only`` reruns chosen scene indices and prints their results without
writing (``--set NAME=VALUE ...`` first changes drawn values in each, e.g. ``pwm_hz=1000``), and
``--report-only`` rewrites the section from the saved results.
"""

from __future__ import annotations

import argparse
import json
import os
import time
from concurrent.futures import ProcessPoolExecutor, as_completed
from pathlib import Path

os.environ.setdefault("NUMBA_NUM_THREADS", "1")  # one core per job: --jobs sets the parallelism

from bench.report import write_section
from bench.scenes.draw import draw, with_values
from bench.scenes.run import earlier_results, run_scene
from bench.scenes.summary import WRONG_FLOW, in_targets, summarise

DOCS = Path(__file__).resolve().parent.parent.parent / "docs"


def _run_index(seed: int, index: int, changes: tuple[str, ...] = ()) -> dict:
    return run_scene(with_values(draw(seed, index), list(changes)))


def run_suite(
    seed: int,
    indices: list[int],
    jobs: int,
    done: dict[int, dict] | None = None,
    changes: tuple[str, ...] = (),
) -> list[dict]:
    """The results of scenes ``indices`` of the suite of ``seed``, in that order (those in
    ``done`` taken from there), each printed as it completes; ``changes``: drawn values
    replaced in each (``with_values``)."""
    done = done or {}
    todo = [i for i in indices if i not in done]
    results = dict(done)
    if jobs <= 1:
        completed = (_run_index(seed, i, changes) for i in todo)
        for n, r in enumerate(completed, 1):
            results[r["draw"]["index"]] = r
            _progress(n, len(todo), r)
        return [results[i] for i in indices]
    with ProcessPoolExecutor(jobs) as pool:
        futures = [pool.submit(_run_index, seed, i, changes) for i in todo]
        for n, future in enumerate(as_completed(futures), 1):
            r = future.result()
            results[r["draw"]["index"]] = r
            _progress(n, len(todo), r)
    return [results[i] for i in indices]


def _progress(n: int, total: int, r: dict) -> None:
    """A line for a person, then the result as one JSON line (``--resume`` reads those)."""
    print(
        f"[scenes] {n}/{total}: scene {r['draw']['index']} lock {r['right_lock_ms']} ms, "
        f"delivered {r['delivered']}, {r['wall_s']:.0f} s\n{json.dumps(r)}",
        flush=True,
    )


def write_report(run: dict, out: Path) -> str:
    """The suite's section of ``out/BENCHMARKS.md`` from a run (``results/scenes.json``)."""
    body = summarise(run["scenes"], run["wall_s"], run["jobs"], run.get("resumed", 0))
    write_section("scenes", "Randomized scene suite", run["command"], body, out / "BENCHMARKS.md")
    return body


def main(argv: list[str] | None = None) -> None:
    parser = argparse.ArgumentParser(
        prog="python -m bench.scenes", description=__doc__.split("\n")[0]
    )
    parser.add_argument("--scenes", type=int, default=240, help="scenes to draw and run")
    parser.add_argument("--seed", type=int, default=0, help="the suite's seed")
    parser.add_argument("--jobs", type=int, default=os.cpu_count(), help="scenes run at once")
    parser.add_argument("--out", type=Path, default=DOCS, help="folder of BENCHMARKS.md")
    parser.add_argument(
        "--only", type=int, nargs="+", help="rerun these scene indices, print, write nothing"
    )
    parser.add_argument(
        "--set",
        nargs="+",
        default=[],
        metavar="NAME=VALUE",
        help="with --only: change these drawn values in each scene first (e.g. pwm_hz=1000)",
    )
    parser.add_argument(
        "--resume",
        type=Path,
        help="take the scenes an earlier run printed (its output) instead of running them again",
    )
    parser.add_argument(
        "--targets-only",
        action="store_true",
        help="run only the drawn scenes that the issue's targets cover",
    )
    parser.add_argument(
        "--report-only",
        action="store_true",
        help="rewrite the section from <out>/results/scenes.json without running",
    )
    args = parser.parse_args(argv)
    if args.set and not args.only:
        parser.error("--set changes the scenes it reruns: give them with --only")
    if args.set:
        try:  # a misspelt name is refused before any scene runs
            with_values(draw(args.seed, args.only[0]), args.set)
        except ValueError as exc:
            parser.error(str(exc))
    saved = args.out / "results" / "scenes.json"
    if args.report_only:
        print(write_report(json.loads(saved.read_text()), args.out))
        return
    indices = args.only or list(range(args.scenes))
    if args.targets_only:
        indices = [i for i in indices if in_targets(draw(args.seed, i).to_dict(), WRONG_FLOW)]
    t0 = time.perf_counter()
    done = earlier_results(args.resume, args.seed) if args.resume else {}
    results = run_suite(args.seed, indices, args.jobs, done, tuple(args.set))
    if args.only:
        print(json.dumps(results, indent=1))
        return
    resumed = sum(i in done for i in indices)
    run = {
        "command": f"python -m bench.scenes --scenes {args.scenes} --seed {args.seed} "
        f"--jobs {args.jobs}" + (" --targets-only" if args.targets_only else ""),
        "wall_s": time.perf_counter() - t0,
        "jobs": args.jobs,
        "resumed": resumed,
        "scenes": results,
    }
    saved.parent.mkdir(parents=True, exist_ok=True)
    saved.write_text(json.dumps(run, indent=1) + "\n")
    print(write_report(run, args.out))


if __name__ == "__main__":
    main()
