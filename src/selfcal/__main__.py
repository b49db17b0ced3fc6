"""``python -m selfcal``: the same command line as the ``selfcal`` script."""

from .cli import main

if __name__ == "__main__":
    main()
