"""The ``rtval`` command line: parses arguments, calls the library, maps results to exit codes.

Each subcommand lives in ``tools/cmd_<name>.py`` with ``add_parser(subparsers)``; the parser it
adds sets ``func(args) -> int``.  Library errors (bad scene, unreadable EXR, missing file)
become one line on stderr and their exit code (2 for a bad scene, option or missing file;
1 means a comparison or validation failed); usage errors exit 64 so that they are never
confused with a command's own codes (``rtval exr diff`` uses 0-4 like idiff).
"""
from __future__ import annotations

import argparse
import importlib
import signal
import sys

COMMANDS = ["check", "render", "convert", "compare", "validate", "exr", "gallery", "bench", "report",
            "stability"]
USAGE_EXIT = 64


class Terminated(BaseException):
    """SIGTERM or SIGHUP: unwinds like Ctrl-C, so that every write in progress removes its
    temporary file and every child process is stopped."""

    def __init__(self, signum: int):
        super().__init__(signum)
        self.signum = signum


# the signal that arrived (a library may wrap the exception it raised: see _interrupted)
_SIGNALLED: list = []


def _terminate(signum, frame):
    from rt_core.outputs import held
    if held(signum):                # a temporary being created: raised again right after
        return
    _SIGNALLED.append(signum)
    raise Terminated(signum)


def _stop(cleanup) -> None:
    """``cleanup()`` of a run stopped by a signal or Ctrl-C, with a second one noted rather
    than raised: coreutils' ``timeout`` signals rtval and its process group, and the second
    SIGTERM broke off the cleanup with a traceback (a helper's review)."""
    quiet = lambda signum, frame: _SIGNALLED.append(signum)
    old = {s: signal.signal(s, quiet) for s in (signal.SIGTERM, signal.SIGHUP, signal.SIGINT)}
    try:
        cleanup()
    finally:
        for s, handler in old.items():
            signal.signal(s, handler)


def _interrupted(e: BaseException):
    """The Terminated or KeyboardInterrupt behind ``e``: Dr.Jit and Mitsuba re-raise an
    exception from Python code they run (a custom op, an if_stmt's branch, a plugin's
    constructor) as a RuntimeError, chained or by its message only."""
    seen = e
    while seen is not None:
        if isinstance(seen, (Terminated, KeyboardInterrupt)):
            return seen
        seen = seen.__cause__ or seen.__context__
    if _SIGNALLED and isinstance(e, RuntimeError):     # (the wrappers' type)
        return Terminated(_SIGNALLED[-1])
    if "KeyboardInterrupt" in str(e):
        return KeyboardInterrupt()
    return None


class Parser(argparse.ArgumentParser):
    def error(self, message):
        # one line, like every other error (the usage is one --help away)
        print(f"{self.prog}: error: {message}{_suggestion(self, message)} "
              f"(see {self.prog} --help)", file=sys.stderr)
        sys.exit(USAGE_EXIT)

    def parse_known_args(self, args=None, namespace=None):
        # an unknown option is the error to report, not the required option it misspells
        # ("--colums 10": "unrecognized --colums (did you mean --columns?)", not "required:
        # --columns")
        args = sys.argv[1:] if args is None else list(args)
        known = {o for a in self._actions for o in a.option_strings}
        sub = next((a for a in self._actions if isinstance(a, argparse._SubParsersAction)),
                   None)
        for tok in args:
            if sub is not None and tok in sub.choices:
                break                           # the subcommand's parser checks the rest
            if tok == "--":
                break
            name = tok.split("=", 1)[0]
            if any(c.isspace() for c in tok):
                continue                        # a value ("--run '--gpu ./ray ...'")
            if name.startswith("--") and name not in known and not any(
                    k.startswith(name) for k in known):
                self.error(f"unrecognized option {name}")
        ns, rest = super().parse_known_args(args, namespace)
        # an option given an empty value ("--report ''", a shell variable unset) is a
        # mistake: it was taken as "not given" and the output silently not written
        for a in self._actions:
            if a.option_strings and getattr(ns, a.dest, None) == "":
                self.error(f"argument {'/'.join(a.option_strings)}: an empty value")
        # one column or row: the course's corner sampling divides by columns - 1 and rows - 1
        # (every command; a scene whose window gives fewer rows is the scene's error, exit 2)
        if getattr(ns, "sampling", "corners") == "corners":
            for name, what in (("columns", "columns"), ("rows", "rows"),
                               ("command_columns", "columns")):
                v = getattr(ns, name, None)
                if v == 1 or (isinstance(v, list) and 1 in v):
                    self.error(f"argument --{name.replace('_', '-')}: 1 {what[:-1]}: the "
                               f"course's corner sampling divides by {what} - 1; give 2 or more"
                               + (" (or --sampling centers)" if hasattr(ns, "sampling")
                                  else ""))
        return ns, rest


def _suggestion(parser, message: str) -> str:
    """' (did you mean X?)' for a misspelt subcommand, choice or option."""
    import difflib
    import re
    m = re.search(r"invalid choice: '([^']*)' \(choose from (.*)\)", message)
    if m:
        choices = re.findall(r"'([^']*)'", m.group(2)) or [c.strip() for c in
                                                          m.group(2).split(",")]
        close = difflib.get_close_matches(m.group(1), choices, n=1)
    else:
        m = re.search(r"unrecognized (?:option|arguments:) (--?[\w-]+)", message)
        if not m:
            return ""
        # (compared without the dashes, which made --bogus 'close' to --verbose)
        known = {o.lstrip("-"): o for a in parser._actions for o in a.option_strings
                 if o.startswith("--")}
        close = [known[k] for k in difflib.get_close_matches(m.group(1).lstrip("-"), known,
                                                              n=1)]
    return f" (did you mean {close[0]}?)" if close else ""


def _version() -> str:
    """The package version, and the git commit when run from a checkout."""
    import os
    import subprocess
    from importlib import metadata
    try:
        v = metadata.version("rtval")
    except metadata.PackageNotFoundError:
        v = "unknown"
    try:
        repo = os.path.dirname(os.path.dirname(os.path.abspath(__file__)))
        commit = subprocess.run(["git", "-C", repo, "rev-parse", "--short=12", "HEAD"],
                                capture_output=True, text=True, timeout=5).stdout.strip()
    except (OSError, subprocess.SubprocessError):
        commit = ""
    return v + (f" (commit {commit})" if commit else "")


class _VersionAction(argparse.Action):
    """``--version``: prints ``rtval VERSION`` and exits, as argparse's own action does."""

    def __init__(self, option_strings, dest, **kw):
        super().__init__(option_strings, dest, nargs=0, default=argparse.SUPPRESS,
                         help="show program's version number and exit")

    def __call__(self, parser, namespace, values, option_string=None):
        sys.stdout.write(f"rtval {_version()}\n")
        parser.exit()


def _refuse_overwriting_inputs(args) -> None:
    """WriteError (exit 2; rtval exr's 4) for an output option naming an input file."""
    from tools.options import outputs_over_inputs
    for opt, out, why in outputs_over_inputs(args):
        from rt_core.outputs import WriteError
        err = WriteError(out, f"{opt} {why}", "write the output elsewhere")
        if args.command == "exr":
            err.exit_code = 4
        raise err


def build_parser() -> argparse.ArgumentParser:
    parser = Parser(prog="rtval", description="Reference harness for the course ray tracer.")
    # (the version is looked up only when asked: the package metadata and a git call took
    # ~24 ms of every command's start)
    parser.add_argument("--version", action=_VersionAction)
    sub = parser.add_subparsers(dest="command", required=True, parser_class=Parser)
    for name in COMMANDS:
        importlib.import_module(f"tools.cmd_{name}").add_parser(sub)
    return parser


def main(argv=None) -> int:
    saved = sys.stdout
    if saved is not None:               # (None: standard output closed, print() skips it)
        sys.stdout = _Stdout(saved)
    try:
        return _main(argv)
    except Exception as e:
        # Ctrl-C while the libraries load (before _run handles it): an import broken off
        # raises other errors on the way (NameError: name '_drjit_ext' ..., exit 1, which
        # check's callers read as a failing scene: a helper's review)
        if not isinstance(_interrupted(e), KeyboardInterrupt):
            raise
        print("rtval: interrupted", file=sys.stderr)
        return 130
    except KeyboardInterrupt:
        print("rtval: interrupted", file=sys.stderr)
        return 130
    finally:
        sys.stdout = saved


def _main(argv) -> int:
    try:
        try:
            args = build_parser().parse_args(argv)
        finally:                        # (--help, --version: what they printed, written)
            if sys.stdout is not None:
                sys.stdout.flush()
    except OSError as e:
        print(f"rtval: {e}", file=sys.stderr)
        return 2
    if hasattr(args, "before_import"):      # e.g. pick Dr.Jit's kernel cache before it loads
        args.before_import(args)
    # (rt_core loads Dr.Jit: imported only now, after before_import; bench and report chose
    # no fresh kernel cache when it came first)
    from rt_core.inputfile import tracking_inputs
    with tracking_inputs():             # (an output may not replace a file the run read)
        return _run(args)


def _run(args) -> int:
    from rt_core.errors import USER_ERRORS
    from rt_core.outputs import cleanup
    _SIGNALLED.clear()                  # (this run's signals only: tests call main again)
    for sig in (signal.SIGTERM, signal.SIGHUP):
        signal.signal(sig, _terminate)
    try:
        _refuse_overwriting_inputs(args)
        code = int(args.func(args) or 0)
        if sys.stdout is not None:
            sys.stdout.flush()          # (a full disk shows here, where it can be said)
        return code
    except Terminated as e:
        _stop(cleanup)
        print(f"rtval: terminated by {signal.Signals(e.signum).name}", file=sys.stderr)
        return 128 + e.signum
    except BrokenPipeError:       # (an OSError: caught before USER_ERRORS)
        # stdout closed early (rtval ... | head) on a write that bypassed _Stdout (binary
        # output): not an error of ours, but the run's verdict is not known
        import os
        os.dup2(os.open(os.devnull, os.O_WRONLY), sys.stdout.fileno())
        return 0
    except USER_ERRORS as e:
        if isinstance(e, OSError) and e.filename:
            msg = f"{e.filename}: {(e.strerror or str(e)).lower()}"
        else:
            msg = str(e).splitlines()[0] if str(e) else type(e).__name__
        print(f"rtval {args.command}: {msg}", file=sys.stderr)
        return getattr(e, "exit_code", 2)
    except KeyboardInterrupt:
        _stop(cleanup)
        print("rtval: interrupted", file=sys.stderr)
        return 130
    except Exception as e:              # a signal that a library wrapped, or a bug of ours
        why = _interrupted(e)
        if why is None:
            raise
        _stop(cleanup)
        if isinstance(why, Terminated):
            print(f"rtval: terminated by {signal.Signals(why.signum).name}", file=sys.stderr)
            return 128 + why.signum
        print("rtval: interrupted", file=sys.stderr)
        return 130


class _Stdout:
    """``sys.stdout`` whose write errors (a full disk, /dev/full) are WriteError naming it,
    with what to do: they read ``[Errno 28] No space left on device``, no file, no fix.  The
    stream then writes to /dev/null, so that the interpreter's last flush does not raise the
    same error again.  A reader that stops early (``rtval check ... | head``) ends the output
    only: the run goes on to its verdict's exit code and its other outputs (--junit,
    --report), which a grading script reads (a helper's review: a failing class exited 0
    and wrote no JUnit file behind ``| true``)."""

    def __init__(self, stream):
        self._stream = stream
        self._error = None              # (raised again by flush: argparse swallows it)

    def _devnull(self):
        import os
        try:
            os.dup2(os.open(os.devnull, os.O_WRONLY), self._stream.fileno())
        except (OSError, ValueError, AttributeError):
            pass

    def _failed(self, e: OSError):
        from rt_core.outputs import WriteError, _HINTS
        self._devnull()
        self._error = WriteError("standard output", (e.strerror or str(e)).lower(),
                                 _HINTS.get(e.errno, "write it elsewhere (redirect it to a "
                                                     "file)"))
        return self._error

    def write(self, text):
        try:
            try:
                return self._stream.write(text)
            except UnicodeEncodeError:
                # a path's bytes that are not UTF-8 (surrogate escapes): written \xNN, as
                # the error lines and the reports write them (an instructor's review:
                # a traceback where a scene's name had such a byte)
                from rt_core.outputs import attr_text
                return self._stream.write(attr_text(text))
        except BrokenPipeError:
            self._devnull()
            return len(text)
        except OSError as e:
            raise self._failed(e) from None

    def flush(self):
        if self._error is not None:
            raise self._error
        try:
            return self._stream.flush()
        except BrokenPipeError:
            self._devnull()
        except OSError as e:
            raise self._failed(e) from None

    def __getattr__(self, name):
        return getattr(self._stream, name)


if __name__ == "__main__":
    sys.exit(main())
