"""octo-harness: closed-loop Octo evaluation in robosuite with per-step attention capture."""
