"""Reports built from metrics.json files: paper-layout tables, error vs run time.

metrics.json (written by mogaf.evaluate) has, per result:
  dataset, scene, ratio, variant, layout, protocol
  methods.<m>.image      psnr, ssim, lpips (+ mpsnr, mssim, mlpips for iPhone layouts)
  methods.<m>.tracking   epe_3d, delta_3d@0.05, delta_3d@0.10, aj, delta_avg, occlusion_accuracy (or null)
  methods.<m>.runtime    total_wall_s: the stages that produced this method's forecast
  grouping               method, ari, mean_iou, ...
  runtime.stages.<s>     wall_s, max_rss_mb (from Snakemake benchmark files)

Modules: metrics_files (load_metrics), tables, runtime, glance.
"""

from .metrics_files import METRIC_SECTIONS, NO_RESULT, load_metrics

__all__ = ["METRIC_SECTIONS", "NO_RESULT", "load_metrics"]
