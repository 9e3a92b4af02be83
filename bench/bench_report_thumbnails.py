"""What the report's camera thumbnails cost (docs/report.md, "Cameras").

Run on demand (never part of the tests)::

    .venv/bin/python bench/bench_report_thumbnails.py [--scenario table3] [--frames 3] [--repeat 5]

Runs one simulator session (no recording, no .rrd), then times, medians of
``--repeat`` runs, in the same process:

* report.html + report.json written by the ``html`` report with the session's
  thumbnails, against the same report of the same summary without them
  (``thumbnails=()``, the baseline), and with ``figures = false``;
* the observer's per-pair work when it keeps a pair (one block-mean reduction
  per camera, :func:`crossfield.report.thumbnails.downsample`) against a
  plain copy of the same image (the memory-bandwidth floor);

and prints the ratios and the sizes of report.html.
"""

from __future__ import annotations

import argparse
import dataclasses
import statistics
import sys
import tempfile
import time
from pathlib import Path

from crossfield.api import run
from crossfield.plugins.report_html import HtmlReport
from crossfield.chain.registry import get_implementation, make_plugin_manager
from crossfield.report.thumbnails import downsample


def median_time(fn, repeat: int) -> float:
    times = []
    for _ in range(repeat):
        t0 = time.perf_counter()
        fn()
        times.append(time.perf_counter() - t0)
    return statistics.median(times)


def main() -> int:
    parser = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    parser.add_argument("--scenario", default="table3")
    parser.add_argument("--frames", type=int, default=3)
    parser.add_argument("--repeat", type=int, default=5)
    args = parser.parse_args()
    with tempfile.TemporaryDirectory() as tmp:
        tmp = Path(tmp)
        summary = run(scenario=args.scenario, frames=args.frames, seed=1, output_dir=tmp, name="s",
                      record=False, rerun=False)
        bare = dataclasses.replace(summary, thumbnails=())
        html = HtmlReport()
        cases = {
            "with thumbnails": lambda: html.write(summary, tmp / "with"),
            "without (baseline)": lambda: html.write(bare, tmp / "without"),
            "figures = false": lambda: HtmlReport(figures=False).write(summary, tmp / "none"),
        }
        times = {name: median_time(fn, args.repeat) for name, fn in cases.items()}
        base = times["without (baseline)"]
        print(f"report of a {args.scenario} session, {args.frames} pairs, median of {args.repeat}:")
        for name, t in times.items():
            folder = {"with thumbnails": "with", "without (baseline)": "without", "figures = false": "none"}[name]
            size = (tmp / folder / "report.html").stat().st_size
            print(f"  {name:<20} {t:7.3f} s  x{t / base:5.2f}   report.html {size / 1000:7.1f} kB")

        frame = summary.thumbnails[0]
        image = first_upper_image(summary)
        t_down = median_time(lambda: downsample(image, 12), max(args.repeat, 20))
        t_copy = median_time(lambda: image.copy(), max(args.repeat, 20))
        print(f"observer, one camera image {image.shape[1]} x {image.shape[0]} px -> 1:{frame.factor}:")
        print(f"  downsample {t_down * 1e3:7.2f} ms, plain copy {t_copy * 1e3:7.2f} ms, x{t_down / t_copy:5.1f}")
    return 0


def first_upper_image(summary):
    """The session's first upper image again (the simulator is deterministic per seed)."""
    config = summary.info.config
    impl = get_implementation(make_plugin_manager(), "acquire", config.stages["acquire"].plugin)
    source = impl.create(dict(config.stages["acquire"].options), "bench")
    try:
        return next(iter(source.frames())).upper
    finally:
        source.close()


if __name__ == "__main__":
    sys.exit(main())
