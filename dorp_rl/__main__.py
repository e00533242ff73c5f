"""``python -m dorp_rl`` is the ``dorp`` command (see :mod:`dorp_rl.cli`)."""

from dorp_rl.cli import main

if __name__ == "__main__":
    main()
