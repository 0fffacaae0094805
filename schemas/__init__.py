"""Pydantic v2 models of the scene manifest and every stage artifact."""
