"""Many scenes through the one DAG: a batch of scenes, each stage of each scene a job.

- `scenes`: which scene folders a command line names (globs, folders of scenes).
- `jobs`: the unit of work, one stage of one scene, as a plain function of plain data, so any
  executor can run it (in this process, or as a Ray task on another machine).
- `executors`: `local` (this process, one job at a time) and `ray` (a Ray cluster); they know
  nothing about stages, only jobs, resources and retries.
- `scheduler`: the DAG inside each scene, scenes side by side, locks, faults, the summary.
- `progress`: the live scenes x stages table (plain lines when not on a terminal).

See docs/scale.md.
"""
