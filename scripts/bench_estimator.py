#!/usr/bin/env python3
"""Benchmark the estimation methods: accuracy and fit time on captures with ground truth.

    python scripts/bench_estimator.py [--captures DIR ...] [--methods default,paper]
                                      [--synthetic N] [--details]

Default captures: ../shared/captures-sample next to the repository. ``--synthetic N``
adds N unseen captures drawn like the sample set (estimator.synthetic.sample_like).
"""
from __future__ import annotations

import argparse
import sys
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT))

from tapecell.estimator import TapecellError  # noqa: E402
from tapecell.estimator.bench import details, run, sample_captures, summary  # noqa: E402
from tapecell.estimator.synthetic import sample_like  # noqa: E402


def main(argv: list[str] | None = None) -> int:
    p = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    p.add_argument("--captures", nargs="*", type=Path, default=None,
                   help="capture folders or folders of captures (default ../shared/captures-sample)")
    p.add_argument("--methods", default="default,paper")
    p.add_argument("--synthetic", type=int, default=0, metavar="N", help="also N synthetic unseen captures")
    p.add_argument("--details", action="store_true", help="one line per capture and method")
    a = p.parse_args(argv)
    methods = [m.strip() for m in a.methods.split(",") if m.strip()]
    dirs = a.captures if a.captures is not None else [ROOT.parent / "shared" / "captures-sample"]
    try:
        captures = [] if a.captures == [] else sample_captures([d for d in dirs if d.exists()])
        tables = []
        if captures:
            rows = run([(c.name, c) for c in captures], methods)
            tables.append(summary(rows, methods, f"captures: {', '.join(str(d) for d in dirs)} ({len(captures)})"))
            if a.details:
                tables.append(details(rows))
        if a.synthetic:
            rows = run([(f"synthetic-{k:03d}", sample_like(k)) for k in range(a.synthetic)], methods)
            tables.append(summary(rows, methods, f"synthetic unseen captures (sample_like 0..{a.synthetic - 1})"))
            if a.details:
                tables.append(details(rows))
    except TapecellError as e:
        print(f"bench_estimator: error: {e}", file=sys.stderr)
        return 2
    if not tables:
        print("bench_estimator: error: no captures with truth.json found", file=sys.stderr)
        return 2
    print("\n\n".join(tables))
    return 0


if __name__ == "__main__":
    sys.exit(main())
