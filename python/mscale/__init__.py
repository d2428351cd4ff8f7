"""mscale from Python: `Client` for the job service (`mscale serve`), and loaders of run
directories (`load_run`) and sweep reports (`load_report`, `sweep`)."""

from .client import Client, Event, Job, JobWorker, MscaleError, scene_files
from .loaders import Run, load_report, load_run, load_snapshots, summary_row, sweep

__all__ = ["Client", "Event", "Job", "JobWorker", "MscaleError", "scene_files", "Run", "load_report", "load_run",
           "load_snapshots", "summary_row", "sweep"]
__version__ = "0.1.0"
