"""`python -m rcan_rtps.rcan.actions`: the actions table of docs/actions.md."""

from ._registry import markdown_table

print(markdown_table(), end="")
