"""octo-harness: closed-loop Octo evaluation in robosuite with per-step attention capture."""

from harness import threadsafe as _threadsafe

_threadsafe.install()  # before any thread reads an array: numpy's .npy header parse is not thread-safe on CPython 3.11
