"""The ``democheck`` command (and ``python -m democheck``).  Ctrl-C at any moment is one line and exit status 130,
whoever answers it: a command (``cli.common.user_errors``), the command line's parser, or this function while the CLI
loads.  Once the command has finished, an interrupt is ignored, so that it cannot turn a finished command's exit
status into a signal's."""

import atexit
import os
import signal
import sys

INTERRUPTED = 130


def main() -> None:
    status = None
    try:
        from democheck.cli import app
        from democheck.cli.common import answer_ctrl_c, ctrl_c_pressed

        answer_ctrl_c()
        app()
    except SystemExit as exc:
        status = exc.code
    except BaseException as exc:
        if not (isinstance(exc, KeyboardInterrupt) or ("ctrl_c_pressed" in locals() and ctrl_c_pressed())):
            raise
        status = INTERRUPTED
    finally:
        signal.signal(signal.SIGINT, signal.SIG_IGN)
    if status != INTERRUPTED:
        raise SystemExit(status)
    print("interrupted; nothing was written", file=sys.stderr)
    # An interrupt that reached code a compiled extension evaluates (mujoco's bindings do) leaves CPython's
    # "unhandled KeyboardInterrupt" mark set although it was handled, and the interpreter would then end by killing
    # itself with SIGINT.  So end here: the exit handlers, the streams, and the status.
    atexit._run_exitfuncs()
    sys.stdout.flush()
    sys.stderr.flush()
    os._exit(INTERRUPTED)


if __name__ == "__main__":
    main()
