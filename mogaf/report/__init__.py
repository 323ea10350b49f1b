"""Reports built from metrics.json files: paper-layout tables, error vs run time.

metrics.json (written by mogaf.evaluate) has, per result:
  dataset, scene, ratio, variant, layout, protocol
  methods.<m>.image      psnr, ssim, lpips (+ mpsnr, mssim, mlpips for iPhone layouts)
  methods.<m>.tracking   epe_3d, delta_3d@0.05, delta_3d@0.10, aj, delta_avg, occlusion_accuracy (or null)
  methods.<m>.runtime    total_wall_s: the stages that produced this method's forecast
  grouping               method, ari, mean_iou, ...
  runtime.stages.<s>     wall_s, max_rss_mb (from Snakemake benchmark files)
"""

from __future__ import annotations

import json
import os
from pathlib import Path
from typing import Any

from ..errors import input_error

NO_RESULT = "no result"


def load_metrics(paths: list[str | os.PathLike]) -> list[dict[str, Any]]:
    """Read metrics.json files; a malformed one fails with one line."""
    out = []
    for path in sorted({str(p) for p in paths}):
        p = Path(path)
        if not p.is_file():
            raise input_error(p, "no such metrics file")
        try:
            data = json.loads(p.read_text())
        except (OSError, json.JSONDecodeError) as exc:
            raise input_error(p, f"not readable JSON ({exc.__class__.__name__})") from None
        if not isinstance(data, dict) or "methods" not in data:
            raise input_error(p, "not a mogaf metrics.json (no 'methods' section)")
        data["_path"] = str(p)
        out.append(data)
    return out
