"""Gate commands over the run store: each reads finished runs (and may run the model again) to decide or show.

regress.py     `octo-harness regress`: a candidate on a baseline's protocol and seeds, stopped when a test decides
replay.py      `octo-harness replay`: a model open loop on the inputs a run recorded
sanity.py      `octo-harness sanity`: the attribution methods' sanity checks on recorded inputs
view.py        `octo-harness view`: a Rerun recording of one episode, rebuilt from the run's files
robustness.py  `octo-harness robustness`: a grid of perturbation kinds x levels run into one folder of runs
config.py      GateConfig: the options of compare, regress and replay, each declared once
"""
