"""Executors: where a run's episodes are run (this process, worker processes, Ray).

The runner (harness/runner.py) plans the episodes, skips what is recorded and writes
every row; an executor only runs episodes and hands each outcome back to the runner's
`on_done` in the parent process, so the run folder keeps a single writer whatever runs
the episodes.
"""
