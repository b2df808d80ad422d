"""Benchmark: the whole correspondence step, SSM Studio vs plain CPD pipelines (all tables).

The entry to the correspondence tables, each in its own module (runnable alone):

- ``bench_corr_pipeline.py``: ``pipeline`` (whole batch vs plain rustcpd CPD-then-project)
  and ``scaling`` (one pair at 2,500 and 10,000 vertices);
- ``bench_corr_spread.py``: ``spread``, ``limits``, ``diagnostics`` and ``model`` (spread of the
  corresponded points around their true material points, and what limits it);
- ``bench_corr_labels.py``: ``labels`` (``mesh-labels`` vs VTK flying edges);
- ``bench_corr_pairs.py``: ``legacy`` (the per-pair table on the demo set vs rustcpd and
  pycpd, pose removal on the demo set, the batch timing).

The peers and metrics are in ``correspondence_common.py`` (also importable from here:
``from bench_correspondence import plain_rustcpd``). With no ``--only``: scaling, spread,
limits, pipeline and labels; diagnostics, model and legacy run only when asked.

Run: ``.venv/bin/python benchmarks/bench_correspondence.py [--only TABLE] [--shapes 18]
[--spread-shapes 8] [--spread-seeds 1] [--population bumps|features] [--param NAME=VALUE]
[--jobs 2] [--tuning]``
"""

from __future__ import annotations

import argparse
import sys
from pathlib import Path

if str(Path(__file__).resolve().parent) not in sys.path:  # imported from elsewhere
    sys.path.insert(0, str(Path(__file__).resolve().parent))

import bench_corr_labels
import bench_corr_pairs
import bench_corr_pipeline
import bench_corr_spread
from correspondence_common import (  # noqa: F401  (the peers, importable from here too)
    area_distortion,
    degenerate_fraction,
    flipped_fraction,
    ours,
    plain_batch,
    plain_batch_timed,
    plain_pycpd,
    plain_rustcpd,
)

TABLES = ("pipeline", "scaling", "spread", "limits", "diagnostics", "model", "labels", "legacy")


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    parser.add_argument("--shapes", type=int, default=18, help="meshes in the pipeline table (18)")
    bench_corr_spread.add_options(parser)
    parser.add_argument("--jobs", type=int, default=2)
    parser.add_argument("--only", choices=TABLES, default=None)
    args = parser.parse_args(argv)
    if args.only in (None, "scaling"):
        bench_corr_pipeline.scaling_table()
    for table in ("spread", "limits", "diagnostics", "model"):
        # diagnostics and model are not in the default run: they explain, they report nothing
        if args.only == table or (args.only is None and table in ("spread", "limits")):
            bench_corr_spread.run(table, args)
    if args.only in (None, "pipeline"):
        bench_corr_pipeline.pipeline_table("ring", args.shapes, args.jobs)
    if args.only in (None, "labels"):
        bench_corr_labels.labels_table()
    if args.only == "legacy":
        return bench_corr_pairs.main([])
    return 0


def legacy_main(argv: list[str] | None = None) -> int:
    """The earlier per-pair table (:func:`bench_corr_pairs.main`)."""
    return bench_corr_pairs.main(argv)


if __name__ == "__main__":
    raise SystemExit(main())
