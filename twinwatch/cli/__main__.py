"""``python -m twinwatch.cli``: the ``twinwatch`` command."""

from twinwatch.cli import main

if __name__ == "__main__":  # pragma: no cover
    main()
