"""Thin Prefect tasks, one module per pipeline stage; ``tasks.common`` holds the cache key,
the stage-task decorator and the store plumbing (``tasks.common.get_task(stage)`` finds a
stage's task)."""
