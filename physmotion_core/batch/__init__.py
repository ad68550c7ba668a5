"""Many videos from one spec: parameter sweeps and datasets (``physmotion batch SPEC -o OUT/``).

``spec`` reads a TOML/YAML spec and expands it into jobs with content-hash ids; ``runner`` runs
the jobs that OUT does not already hold (verified), on a local process pool (the default), a Ray
cluster (``--ray``) or a ComfyUI server (``--comfy``), retrying jobs whose worker died; ``manifest``
writes each job's record and the batch manifest. See docs/batch.md.
"""

from .runner import BatchSummary, run_batch
from .spec import BatchSpec, Job, SpecError, load_spec, physics_version

__all__ = ["BatchSpec", "BatchSummary", "Job", "SpecError", "load_spec", "physics_version", "run_batch"]
