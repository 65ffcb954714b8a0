"""Measures: the pure maths the closed loop computes at a step and the writers and run store store: attention slicing
and readout measures, attribution methods, deletion and imputation fills, the attention controls' frame transforms,
success statistics (summary.csv). Below the policy; nothing here reads a run folder."""
