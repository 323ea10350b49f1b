"""`python -m mogaf.report glance METRICS.json... [--write FILE | --check FILE]`,
`python -m mogaf.report scenes METRICS.json... [--json FILE --run TEXT | --check FILE]`,
`python -m mogaf.report timing PIPELINE.json [--write FILE | --check FILE]` and
`python -m mogaf.report results [METRICS.json...] [--bench DIR] [--write FILE | --check FILE]`.

glance: print the results-at-a-glance table (mogaf.report.glance) made from
metrics.json files; --write puts it between the `<!-- glance:start -->` and
`<!-- glance:end -->` markers of a Markdown file (the README), --check exits 1
when that section differs from what the files give. scenes: print a table
per observation ratio, a row per scene (mogaf.report.scenes); --json also
keeps the results in a scene-rows file for results/bench/, --check exits 1
when a result's measured values differ from such a file's. results: the
measured-results page (docs/results.md) from the benchmark rows in
results/bench/ and any metrics.json files (mogaf.report.results_page);
--write rewrites FILE with it, --check exits 1 when FILE differs. timing:
the README's timing line (mogaf.report.timing) from one
`python -m mogaf.bench pipeline --json` file, between the timing markers.
"""

from __future__ import annotations

import argparse
import sys

from ..errors import MogafError
from .glance import glance, section_matches, write_section
from .metrics_files import load_metrics
from .results_page import BENCH_DIR, command, page_matches, results_page, write_page
from .scenes import check_scene_rows, scenes_table, write_scene_rows
from .timing import MARKERS, timing_line


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(prog="python -m mogaf.report", description=__doc__.split("\n\n")[1])
    sub = parser.add_subparsers(dest="command", required=True)
    p = sub.add_parser("glance", help="results-at-a-glance table (method x PSNR / LPIPS / mPSNR / tracking EPE)")
    p.add_argument("metrics", nargs="+", help="metrics.json files (written by the evaluate stage)")
    out = p.add_mutually_exclusive_group()
    out.add_argument("--write", metavar="FILE", help="rewrite FILE's section between the glance markers")
    out.add_argument("--check", metavar="FILE", help="exit 1 if FILE's glance section differs from the table")
    p = sub.add_parser("scenes", help="per-scene PSNR / LPIPS of every method, a table per ratio, with the mean")
    p.add_argument("metrics", nargs="+", help="metrics.json files (written by the evaluate stage)")
    p.add_argument("--json", metavar="FILE", help="also keep the results in this scene-rows file (results/bench/)")
    p.add_argument("--run", default="", help="with --json: where and how they were measured (machine, commit, date)")
    p.add_argument(
        "--check",
        metavar="FILE",
        help="print no table: exit 1 unless each result repeats the measured values this scene-rows file keeps for it",
    )
    p = sub.add_parser("results", help="the measured-results page (docs/results.md) from results/bench/ rows")
    p.add_argument("metrics", nargs="*", help="metrics.json files to add (glance and per-scene tables)")
    p.add_argument("--bench", default=str(BENCH_DIR), metavar="DIR", help=f"benchmark rows (default: {BENCH_DIR})")
    out = p.add_mutually_exclusive_group()
    out.add_argument("--write", metavar="FILE", help="write the page to FILE")
    out.add_argument("--check", metavar="FILE", help="exit 1 if FILE is not the page these files give")
    p = sub.add_parser("timing", help="the README's timing line from a `python -m mogaf.bench pipeline --json` file")
    p.add_argument("pipeline", help="the benchmark file (results/bench/pipeline_demo_cpu.json)")
    out = p.add_mutually_exclusive_group()
    out.add_argument("--write", metavar="FILE", help="rewrite FILE's section between the timing markers")
    out.add_argument("--check", metavar="FILE", help="exit 1 if FILE's timing section differs from the line")
    args = parser.parse_args(argv)

    try:
        if args.command == "scenes":
            if bool(args.run.strip()) != bool(args.json):
                raise MogafError("scenes: --json FILE and --run TEXT (where the results were measured) go together")
            if args.check and args.json:
                raise MogafError("scenes: --check FILE compares with a kept file, --json FILE writes one: not both")
            results = load_metrics(args.metrics)
            if args.check:
                lines, same = check_scene_rows(args.check, results)
                print("\n".join(lines))
                return 0 if same else 1
            table = scenes_table(results)
            if args.json:  # first: a bad --json or --run prints nothing
                write_scene_rows(args.json, results, args.run)
                print(f"{args.json}: {len(results)} results kept", file=sys.stderr)
            sys.stdout.write(table)
            return 0
        if args.command == "results":
            return _results(args)
        if args.command == "timing":
            return _write_or_check(
                args,
                timing_line(args.pipeline),
                lambda path, text: write_section(path, text, MARKERS),
                lambda path, text: section_matches(path, text, MARKERS),
                "timing section ",
                args.pipeline,
                f"python -m mogaf.report timing {args.pipeline} --write {args.check}",
            )
        block = glance(args.metrics)
        return _write_or_check(
            args,
            block,
            write_section,
            section_matches,
            "glance section ",
            f"{', '.join(args.metrics)}",
            f"python -m mogaf.report glance {' '.join(args.metrics)} --write {args.check}",
        )
    except MogafError as exc:
        print(f"mogaf.report: error: {exc}", file=sys.stderr)
        return 1
    return 0


def _results(args: argparse.Namespace) -> int:
    target = args.write or args.check or "docs/results.md"
    page = results_page(target, args.bench, args.metrics)
    return _write_or_check(
        args, page, write_page, page_matches, "", f"what {args.bench} gives", command(target, args.bench, args.metrics)
    )


def _write_or_check(args, text, write, matches, what: str, sources: str, rewrite: str) -> int:
    """--write FILE, --check FILE (exit 1 naming the command that rewrites it), or print `text`."""
    if args.write:
        changed = write(args.write, text)
        print(f"{args.write}: {what}{'rewritten' if changed else 'already up to date'}")
    elif args.check:
        if not matches(args.check, text):
            print(f"{args.check}: {what}differs from {sources}; rewrite it with: {rewrite}", file=sys.stderr)
            return 1
        print(f"{args.check}: {what}up to date")
    else:
        sys.stdout.write(text)
    return 0


if __name__ == "__main__":
    sys.exit(main())
