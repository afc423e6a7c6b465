"""VoxNeRF REST service: upload scans, run training jobs on Celery workers, render poses (FastAPI)."""
