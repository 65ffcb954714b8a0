"""What a run folder holds, read by every stage above it: the schema check of its manifest and rows (with the
confinement and integrity of the files they name) and the platform record its numbers came from.

It sits below `harness/analysis/` and `harness/run/` so that both read a run folder through one check without
either importing the other backwards (see tests/test_layout.py for the stage order).
"""
