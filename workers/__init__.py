"""Celery workers: ``render`` (θ → image and box) and ``train`` (images → model and score)."""
