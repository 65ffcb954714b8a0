"""Analysis: attention maths, success statistics, paired and sequential tests, run reading, aggregation, comparison."""
