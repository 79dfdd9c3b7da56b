"""The whole pipeline, stage by stage, resumable."""
