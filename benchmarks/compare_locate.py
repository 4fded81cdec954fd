"""Association + solve per frame, this tree's ``locate_frame`` against another commit's, in one run.

The other commit's ``locate.py`` and ``_locate_kernels.py`` (``git show REF:...``) are
loaded as a package of their own beside ``echoloc``, so both run in the same process
on the same echoes (those of ``bench_locate.py``'s scene, or with ``--reflectors N``
those of ``echoloc.benchmark.bench_scene(N)``, N random reflectors in every frame),
in alternating rounds: on this shared, noisy machine only the ratio of the two means
much. Every frame's objects must come out the same in both (positions, covariances,
chi2 and scores bit for bit, support and order), else the script stops.

    python benchmarks/compare_locate.py --base main --frames 1000 --rounds 5
    python benchmarks/compare_locate.py --base main --frames 1000 --rounds 5 --reflectors 5
"""

from __future__ import annotations

import argparse
import importlib
import statistics
import subprocess
import sys
import tempfile
import time
import tomllib
from pathlib import Path
from types import ModuleType
from typing import Any

import numpy as np

from echoloc import pipeline
from echoloc.benchmark import bench_scene
from echoloc.localise import locate
from echoloc.sim.scenefile import scene_from_dict
from echoloc.sim.simulation import simulate

ROOT = Path(__file__).resolve().parents[1]


def _base_locate(ref: str) -> ModuleType:
    """``echoloc.localise.locate`` as of ``ref``, as the module ``echoloc_base_<sha>.locate``."""
    sha = subprocess.run(
        ["git", "rev-parse", ref], cwd=ROOT, check=True, capture_output=True, text=True
    ).stdout.strip()
    name = f"echoloc_base_{sha[:12]}"
    home = Path(tempfile.gettempdir()) / name  # kept: numba's cache of the base compiles once
    package = home / name
    package.mkdir(parents=True, exist_ok=True)
    (package / "__init__.py").write_text("")
    for module in ("locate", "_locate_kernels"):
        for folder in ("src/echoloc/localise", "src/echoloc"):  # the layout since, and before, 0.2
            shown = subprocess.run(
                ["git", "show", f"{sha}:{folder}/{module}.py"], cwd=ROOT, capture_output=True, text=True
            )
            if shown.returncode == 0:
                break
        shown.check_returncode()
        text = shown.stdout
        for old in ("from echoloc.localise import _locate_kernels", "from echoloc import _locate_kernels"):
            text = text.replace(old, f"from {name} import _locate_kernels")
        path = package / f"{module}.py"
        if not path.exists() or path.read_text() != text:
            path.write_text(text)
    sys.path.insert(0, str(home))
    return importlib.import_module(f"{name}.locate")


def _same(a: Any, b: Any) -> bool:
    """The same objects, bit for bit."""
    return len(a.objects) == len(b.objects) and all(
        np.array_equal(x.position_m, y.position_m)
        and np.array_equal(x.covariance_m2, y.covariance_m2)
        and (x.receivers, x.echo_indices, x.transmitters, x.shared)
        == (y.receivers, y.echo_indices, y.transmitters, y.shared)
        and (x.chi2, x.score) == (y.chi2, y.score)
        for x, y in zip(a.objects, b.objects, strict=True)
    )


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--base", default="main", help="commit or branch to compare with")
    parser.add_argument("--frames", type=int, default=1000)
    parser.add_argument("--rounds", type=int, default=5)
    parser.add_argument(
        "--reflectors", type=int, default=None, help="bench_scene(N) instead of the example scene"
    )
    args = parser.parse_args()

    base = _base_locate(args.base)
    if args.reflectors is None:
        data = tomllib.loads((ROOT / "src" / "echoloc" / "scenes" / "random-1m3-six.toml").read_text())
        scene = scene_from_dict(data, "random-1m3-six.toml")
    else:
        scene = bench_scene(args.reflectors)
    recording = simulate(scene, args.frames)
    chain = pipeline.prepare(recording)
    echoes = [pipeline.frame_echoes(chain, i) for i in range(recording.n_frames)]
    assert recording.truth_positions_m is not None
    counts = np.sum(np.isfinite(recording.truth_positions_m[:, :, 0]), axis=1)
    call = (recording.transmitters_m[0], recording.receivers_m, chain.locate_options, chain.usable_receivers)
    for e in echoes:  # compiles both (cached after the first run) and checks the results
        if not _same(locate.locate_frame(e, *call), base.locate_frame(e, *call)):
            raise SystemExit(f"frame {e.frame}: objects differ from {args.base}'s")
    print(f"| reflectors | frames | {args.base} ms/frame | this tree ms/frame | ratio |")
    print("|---|---|---|---|---|")
    for k in range(1, 7):
        group = [echoes[i] for i in np.flatnonzero(counts == k)]
        if not group:
            continue
        times: dict[str, list[float]] = {"base": [], "here": []}
        for _ in range(args.rounds):
            for label, module in (("base", base), ("here", locate)):
                start = time.perf_counter()
                for e in group:
                    module.locate_frame(e, *call)
                times[label].append((time.perf_counter() - start) / len(group))
        theirs, ours = statistics.median(times["base"]), statistics.median(times["here"])
        print(
            f"| {k} | {len(group)} | {theirs * 1e3:.3f} | {ours * 1e3:.3f} | {ours / theirs:.2f} |",
            flush=True,
        )


if __name__ == "__main__":
    main()
