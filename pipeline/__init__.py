"""DAG engine, CLI and run-folder handling of pano-pipe."""
