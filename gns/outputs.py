"""Kept only for pipelines/speed_accuracy.py, which imports check_writable from here: the checks
live in datagen.outputs. Delete this file once that import names datagen.outputs."""
from datagen.outputs import check_json_output, check_writable, overlapping  # noqa: F401
