"""``python -m vflpcd``: the ``vflpcd`` command."""

from vflpcd.app.cli import main

if __name__ == "__main__":          # process workers (spawn) import this module again
    raise SystemExit(main())
