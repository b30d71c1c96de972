"""``python -m vflpcd``: the ``vflpcd`` command."""

from vflpcd.cli import main

if __name__ == "__main__":          # process workers (spawn) import this module again
    raise SystemExit(main())
