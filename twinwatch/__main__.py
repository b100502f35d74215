"""python -m twinwatch."""

from twinwatch.cli import main

main()
