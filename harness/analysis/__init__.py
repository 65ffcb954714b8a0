"""Analysis: success statistics, paired and sequential tests, run reading, aggregation, comparison."""
