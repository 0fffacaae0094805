"""Files pano-pipe reads, writes and deletes: the lowest layer (it imports nothing of pano-pipe).

- `errors`: PanoError, the one-line bad-input error, and reading a user's JSON.
- `paths`: the path rule: scene files stay in the scene folder; run-folder files are opened
  only through `run_path` / `open_run_folder`, which refuse symbolic links inside a run folder.
- `fsutil`: atomic folders and files, the run folder's lock, appending to its log.
- `limits`: decode limits checked from file headers (images, depth maps, .npy, PLY, COLMAP).

Stages, schemas, the importers, the viewer and the CLI import these; docs/security.md says
what each rule guards against.
"""
