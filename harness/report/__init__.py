"""Report: figures (matplotlib Agg), HTML building blocks and the report builder (`octo-harness report`)."""
