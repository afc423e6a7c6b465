"""Celery workers of the VoxNeRF service: a ``train`` queue (one job per process) and a ``render`` queue."""
