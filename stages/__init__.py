"""Stages of the pipeline, one module each; pipeline/registry.py wires them into the DAG."""
