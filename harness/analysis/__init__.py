"""Analysis of finished run folders, offline, above the run store: the run reader, aggregation, comparison, paired and
sequential tests, robustness, phases, grounding, position and sanity analysis, provenance."""
