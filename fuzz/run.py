"""The long fuzz run: thousands of hostile inputs through echoloc, with their counts.

    .venv/bin/python fuzz/run.py                       # the issue's counts (about an hour)
    .venv/bin/python fuzz/run.py --scale 0.05          # a quick look
    .venv/bin/python fuzz/run.py --only recordings --seed 3

Every case must end in exit 0 or a clean exit 2 within 10 s and under 1 GiB, with no
traceback (see ``fuzz/harness.py``). The counts go to stdout and, with ``--report``, to a
Markdown file; the first input of every kind of finding is printed so it can be replayed.
Exit status 1 when anything was found.
"""

from __future__ import annotations

import argparse
import random
import sys
import tempfile
import time
from pathlib import Path

sys.path.insert(0, str(Path(__file__).resolve().parent))

import harness  # fuzz/ ships with the repository, not the wheel: found through sys.path

TARGETS = {"recordings": 10_000, "scenes": 2_000, "calibrations": 600, "sessions": 2_000}


def main() -> int:
    parser = argparse.ArgumentParser(
        description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter
    )
    parser.add_argument("--seed", type=int, default=0, help="the run's random seed")
    parser.add_argument("--scale", type=float, default=1.0, help="fraction of the issue's case counts")
    parser.add_argument("--only", choices=sorted(TARGETS), action="append", help="run only these families")
    parser.add_argument("--report", type=Path, help="also write the counts as Markdown here")
    args = parser.parse_args()
    families = args.only or list(TARGETS)
    tally = harness.Tally()
    started = time.monotonic()
    with tempfile.TemporaryDirectory(prefix="echoloc-fuzz-") as scratch, harness.Worker() as worker:
        folder = Path(scratch)
        seeds = harness.make_seeds(worker, folder / "seeds")
        for name in families:
            count = max(1, round(TARGETS[name] * args.scale))
            rng = random.Random(f"{args.seed}:{name}")
            family_start = time.monotonic()
            if name == "sessions":
                import sessions

                sessions.run_sessions(seeds, rng, tally, count, folder / "sessions")
            else:
                family = harness.FAMILIES[name]
                for index in range(count):
                    harness.run_family(worker, seeds, family, rng, tally, folder / "case")
                    if (index + 1) % 500 == 0:
                        print(f"  {name}: {index + 1}/{count}", file=sys.stderr, flush=True)
            print(
                f"{name}: {count} cases in {time.monotonic() - family_start:.0f} s",
                file=sys.stderr,
                flush=True,
            )
        restarts, reruns = worker.restarts, (worker.reruns, worker.hang_reruns)
    report = render(tally, args, time.monotonic() - started, restarts, reruns)
    print(report)
    if args.report:
        args.report.write_text(report)
    return 0 if tally.clean else 1


def render(
    tally: harness.Tally, args: argparse.Namespace, seconds: float, restarts: int, reruns: tuple[int, int]
) -> str:
    """The counts as a Markdown report."""
    lines = [
        "# Fuzz run",
        "",
        f"`.venv/bin/python fuzz/run.py --seed {args.seed} --scale {args.scale:g}`: "
        f"{sum(tally.cases.values())} cases in {seconds / 60:.1f} min, worker restarts {restarts} "
        f"(cases judged again alone in a fresh worker: {reruns[0]} for their memory, "
        f"{reruns[1]} past the time bound), "
        f"slowest case {tally.slowest_s:.2f} s, peak resident memory {tally.peak_rss_bytes / 2**20:.0f} MiB.",
        "",
        "| family | cases | exit 0 | exit 2 | hangs > 10 s | tracebacks | exit 1 | over 1 GiB | other |",
        "|---|---:|---:|---:|---:|---:|---:|---:|---:|",
    ]
    for family, cases in tally.cases.items():
        problems = {problem: n for (name, problem), n in tally.problems.items() if name == family}
        other = sum(
            n for problem, n in problems.items() if problem not in ("hang", "traceback", "exit 1", "memory")
        )
        lines.append(
            f"| {family} | {cases} | {tally.exits[family, '0']} | {tally.exits[family, '2']} | "
            f"{problems.get('hang', 0)} | {problems.get('traceback', 0)} | {problems.get('exit 1', 0)} | "
            f"{problems.get('memory', 0)} | {other} |"
        )
    if tally.notes:
        lines += ["", *(f"- {name}: {value}" for name, value in tally.notes.items())]
    if tally.examples:
        lines += ["", "First input of each finding:", ""]
        lines += [
            f"- {family}, {problem}: {example}"
            for (family, problem), example in sorted(tally.examples.items())
        ]
    return "\n".join(lines) + "\n"


if __name__ == "__main__":
    sys.exit(main())
