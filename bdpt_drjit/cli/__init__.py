"""The ``bdpt`` command line: render, merge and inspect scenes.

    bdpt render [SCENE.xml] [-o out.exr] [--spp N] [--seed N] [--time SECONDS]
                [--checkpoint SECONDS] [--res WxH] [-D key=value ...] [--sensor N]
                [--variant llvm_ad_rgb] [renderer settings] [--strategy-images] [--quiet]
                [--cluster local:N|auto|ray://HOST:PORT]
    bdpt mlt [SCENE.xml] [-o out.exr] [--spp MUTATIONS] [--time SECONDS] [pssmlt options]
    bdpt merge a.exr b.exr ... -o out.exr
    bdpt info [SCENE.xml] [-D key=value ...] [--sensor N]
    bdpt info IMAGE.exr

The renderer settings are the integrator's parameters (``bdpt_drjit.settings.PARAMS``)
as options: ``--max-depth N``, ``--mis power``, ``--strategy-subset pt``,
``--no-light-image``, ... (``bdpt render --help``).  ``python -m bdpt_drjit ...`` is
the same command.  ``bdpt SCENE.xml ...`` is short for ``bdpt render SCENE.xml ...``.

Rendering is progressive: the renderer works in passes, and the command stops
cleanly after the current pass on Ctrl-C (SIGINT) or SIGTERM, or once the
``--time`` budget is used up, and writes the image of the passes done; after a
signal the exit status is 130 (SIGINT) or 143 (SIGTERM).  The EXR header records
what the image is: ``spp`` (int), ``seed``, ``passes``, ``render_time``, ``scene``,
``bdpt_version`` and the settings, so that ``bdpt merge`` can combine independent
renders (different seeds) weighted by their spp, and ``bdpt info`` can show it.
Files are replaced atomically, so an interrupted write never leaves a broken file.

With ``--cluster`` the passes run on Ray workers and are merged in pass order
(``bdpt_drjit.cluster``): the same image as a local render of the seed, the same stops.

Errors in the input (missing or malformed scene, unsupported plugins, bad
options, an unwritable output, no usable LLVM) are reported as one line on
stderr with a non-zero exit status; set ``BDPT_DEBUG=1`` for a traceback.

Modules: ``args`` (the parser), ``scene`` (variant, scene, renderer), one module
per command (``render``, ``mlt``, ``merge``, ``info``), ``images`` (EXR/PNG output),
``progress`` (progress bar, stop requests), ``errors`` (one-line reports).
"""
from __future__ import annotations

import importlib
import os
import sys
import warnings

from .args import parse_args
from .errors import CLIError, Interrupted, eprint, one_line
from .progress import StopRequest, exit_status

__all__ = ["main", "CLIError"]


def _showwarning(message, category, filename, lineno, file=None, line=None):
    eprint("bdpt: warning: %s" % one_line(message))


def _run(argv, stop) -> int:
    stop.check()               # a signal that arrived while bdpt_drjit was imported
    args = parse_args(argv)
    return importlib.import_module("." + args.command, __name__).run(args, stop)


def main(argv=None) -> int:
    """Run the command line; returns the exit status."""
    argv = sys.argv[1:] if argv is None else list(argv)
    with warnings.catch_warnings(), StopRequest() as stop:
        warnings.showwarning = _showwarning
        # Renamed parameters in a scene's bdpt integrator: say so.
        warnings.filterwarnings("default", message="bdpt:", category=DeprecationWarning)
        try:
            return _run(argv, stop)
        except CLIError as e:
            eprint("bdpt: error: %s" % e)
            return e.code
        except Interrupted as e:
            eprint("bdpt: interrupted (%s); nothing was written" % e)
            return exit_status(e.signum)
        except KeyboardInterrupt:          # a second signal
            eprint("\nbdpt: aborted; nothing more was written")
            return exit_status(stop.signal or 2)
        except BrokenPipeError:
            return 1
        except Exception as e:
            if os.environ.get("BDPT_DEBUG"):
                raise
            eprint("bdpt: error: %s: %s (set BDPT_DEBUG=1 for a traceback)"
                   % (type(e).__name__, one_line(e)))
            return 1


if __name__ == "__main__":
    sys.exit(main())
