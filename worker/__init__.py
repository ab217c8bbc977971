"""Celery worker: claims jobs from the database and runs drop_engine on them."""
