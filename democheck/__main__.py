"""The ``democheck`` command (and ``python -m democheck``): the CLI, imported here so that Ctrl-C while it loads --
before any command can answer it -- is one line and exit status 130 too, never a traceback."""

import sys


def main() -> None:
    try:
        from democheck.cli import app
    except KeyboardInterrupt:
        print("interrupted; nothing was written", file=sys.stderr)
        raise SystemExit(130) from None
    app()


if __name__ == "__main__":
    main()
