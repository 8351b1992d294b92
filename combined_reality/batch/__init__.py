"""Many cylinders at once: a manifest of cylinders (manifest), each identified as one task
on local processes or a dask cluster, incremental by content hash (execution), the
compiled model code shipped to cluster workers (cluster), and the fleet report (report)."""
from .cluster import share_compiled_code
from .execution import BatchSummary, read_results_csv, run_batch, run_job
from .manifest import MODELS_HELP, CylinderJob, ManifestError, SimulateSpec, load_manifest
from .report import render_batch_report, write_batch_report

__all__ = ["share_compiled_code", "BatchSummary", "read_results_csv", "run_batch", "run_job", "MODELS_HELP",
           "CylinderJob", "ManifestError", "SimulateSpec", "load_manifest", "render_batch_report",
           "write_batch_report"]
