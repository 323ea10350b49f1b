"""python -m mogaf.synth OUT_DIR [--preset hard] [--set key=value ...] [--preview sheet.png]"""

from __future__ import annotations

import argparse
import json
import sys
import time

from ..errors import MogafError
from .generate import generate_scene
from .params import PRESETS
from .preview import contact_sheet


def _value(text: str):
    try:
        return json.loads(text)
    except json.JSONDecodeError:
        return text


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(
        prog="python -m mogaf.synth", description="Generate a synthetic scene in the DyCheck iPhone layout."
    )
    ap.add_argument("out_dir")
    ap.add_argument("--preset", default="default", choices=sorted(PRESETS))
    ap.add_argument(
        "--set", action="append", default=[], metavar="KEY=VALUE", help="override a generator parameter (JSON value)"
    )
    ap.add_argument("--preview", metavar="PNG", help="also write a contact sheet")
    args = ap.parse_args(argv)
    params = {"preset": args.preset}
    try:
        for item in args.set:
            if "=" not in item:
                raise MogafError(f"--set expects KEY=VALUE, got {item!r}")
            key, value = item.split("=", 1)
            params[key.strip()] = _value(value)
        start = time.perf_counter()
        out = generate_scene(args.out_dir, params)
        print(f"wrote {out} in {time.perf_counter() - start:.1f} s")
        if args.preview:
            print(f"wrote {contact_sheet(out, args.preview)}")
    except MogafError as exc:
        print(f"mogaf.synth: error: {exc}", file=sys.stderr)
        return 1
    return 0


if __name__ == "__main__":
    sys.exit(main())
