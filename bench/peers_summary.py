"""Summaries of ``bench_calibrate_peers.py --json`` rows over the first N seeds (issue 28).

    .venv/bin/python bench/peers_summary.py /tmp/peers40.json --seeds 20 40
    .venv/bin/python bench/peers_summary.py /tmp/peers40.json --seeds 21-40
    .venv/bin/python bench/peers_summary.py /tmp/peers_mm.json

For each entry of ``--seeds`` (``N``: seeds 1..N; ``A-B``: seeds A..B;
default: every seed in the file) and each view count in the file, over the
rows of those seeds it prints:

* the bench's own table of medians per tool (``bench_calibrate_peers.table``:
  focal length, principal point, rotation, translation errors, the share
  within 2 stated std, solve time, views dropped);
* crossfield's median / the better peer's median (the smaller of OpenCV's
  and mrcal's, named) for rotation, translation and focal length, against
  issue 28's target of at most 1.1;
* the paired per-seed ratios crossfield / mrcal (same detections): their
  geometric mean and the number of seeds in which crossfield's error is the
  smaller, for focal length, rotation and translation.

Nothing is solved again: it reads the rows only.
"""

from __future__ import annotations

import argparse
import json
import sys
from pathlib import Path

import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parent))

from bench_calibrate_peers import table  # noqa: E402

KEYS = (("rot_arcsec", "rotation"), ("T_mm", "translation"), ("f_rel", "focal length"))
TARGET = 1.1


def medians(rows: list[dict], pairs: int, key: str) -> dict[str, float]:
    """Median of ``key`` per tool over the rows at ``pairs`` view pairs."""
    out = {}
    for tool in ("crossfield", "opencv", "mrcal"):
        values = [r[key] for r in rows if r["pairs"] == pairs and r["tool"] == tool]
        if values:
            out[tool] = float(np.median(values))
    return out


def ratio_lines(rows: list[dict], pairs: int) -> list[str]:
    """crossfield's median / the better peer's, per quantity."""
    lines = []
    for key, name in KEYS:
        med = medians(rows, pairs, key)
        peer = min(("opencv", "mrcal"), key=lambda t: med.get(t, np.inf))
        ratio = med["crossfield"] / med[peer]
        verdict = "within 1.1" if ratio <= TARGET else "ABOVE 1.1"
        lines.append(
            f"{pairs} pairs {name}: crossfield {med['crossfield']:.4g} / {peer} {med[peer]:.4g}"
            f" = {ratio:.3f} ({verdict})"
        )
    return lines


def paired_lines(rows: list[dict], pairs: int) -> list[str]:
    """Per-seed crossfield / mrcal on the same detections: geometric mean, seeds crossfield is better."""
    by = {(r["seed"], r["tool"]): r for r in rows if r["pairs"] == pairs}
    seeds = sorted({s for s, t in by if t == "crossfield" and (s, "mrcal") in by})
    lines = []
    for key, name in KEYS:
        ratios = np.array([by[(s, "crossfield")][key] / by[(s, "mrcal")][key] for s in seeds])
        better = int(np.sum(ratios < 1))
        lines.append(
            f"{pairs} pairs {name}: paired crossfield / mrcal"
            f" geometric mean {np.exp(np.mean(np.log(ratios))):.2f},"
            f" crossfield better in {better} of {len(seeds)} seeds"
            f" (per-seed ratios {ratios.min():.2f}-{ratios.max():.2f})"
        )
    return lines


def seed_range(text: str) -> tuple[int, int]:
    """``N`` -> (1, N); ``A-B`` -> (A, B)."""
    first, _, last = text.partition("-")
    return (int(first), int(last)) if last else (1, int(first))


def summary(rows: list[dict], first: int, last: int) -> str:
    """The tables and ratios over seeds first..last."""
    sel = [r for r in rows if first <= r["seed"] <= last]
    pairs = sorted({r["pairs"] for r in sel})
    present = sorted({r["seed"] for r in sel})
    out = [f"## seeds {first}-{last} ({len(present)} seeds present)", "", table(sel, pairs), ""]
    for n in pairs:
        out += ratio_lines(sel, n)
    out.append("")
    for n in pairs:
        out += paired_lines(sel, n)
    return "\n".join(out)


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("json", type=Path, help="bench_calibrate_peers.py --json output")
    ap.add_argument(
        "--seeds",
        type=seed_range,
        nargs="+",
        default=None,
        help="N (seeds 1..N) or A-B (seeds A..B), each summarised",
    )
    args = ap.parse_args(argv)
    rows = json.loads(args.json.read_text())
    for first, last in args.seeds or [(1, max(r["seed"] for r in rows))]:
        print(summary(rows, first, last))
        print()
    return 0


if __name__ == "__main__":
    sys.exit(main())
