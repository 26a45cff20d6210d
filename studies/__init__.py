"""Research that served a design decision: runnable from a checkout, not installed.

Each module runs as ``python -m studies.NAME`` from the repository root; its
conclusions are in ``docs/design.md``.
"""
