"""The serve loop of the Python plant drivers: the agent's line protocol
(plant-agent/DRIVER.md) on stdin/stdout, written once so that the drivers cannot drift
apart in what they accept. A driver defines its model and calls `run(model, channels)`.

The model (any object with these four methods)
    read()          -> the N outputs measured now, a sequence of N floats
    write(values)   -> the N inputs applied from now on, after the actuator's limits;
                       `values` is a list of N finite floats
    advance(dt)     -> integrate dt seconds, 0 <= dt <= MAX_ADVANCE (a simulation; a real rig
                       ignores it)
    safe_stop()     -> every input to 0

The protocol (one answer per request, flushed)
    (start)          -> hello channels=N
    read             -> y_1 ... y_N
    write v_1 .. v_N -> ok a_1 ... a_N          (what was applied)
    advance DT       -> ok
    stop             -> ok, safe stop, exit 0
    end of stdin     -> safe stop, exit 0 (also on a broken stdout or Ctrl-C)
    anything else    -> err MESSAGE, and nothing changes (inputs, plant, noise stream)

Limits: a request that breaks one is refused with `err` before the model sees it
    MAX_LINE       4096 characters per request: a `write` of 64 channels at full precision
                   takes under 1,700. A longer line is read to its end and refused whole.
    MAX_ADVANCE    60 s per `advance` (split longer waits): the work of one request stays
                   bounded, so the driver answers within the agent's timeout.
    MAX_CHANNELS   64, the protocol's limit on N.
    numbers        ASCII decimal floats (`1.5`, `-2e-3`, `7`), finite: not `nan`, `inf`,
                   `1e999` (it overflows), `1_0` or other digits Python's float() accepts.
    arity          `read` and `stop` take nothing, `advance` one number, `write` exactly N.
The model's answers are checked as well: N finite numbers, or `err` (a model's bug is
reported to the agent, which ends the run, rather than a NaN sent to the controller).

Standard library only. The drivers import this file by its place beside their folders
(`plants/driver_loop.py`), so they run from any working directory.
"""

import math
import os
import re
import sys

MAX_LINE = 4096  # characters per request, newline excluded
MAX_ADVANCE = 60.0  # s per `advance`
MAX_CHANNELS = 64

_NUMBER = re.compile(r"[+-]?(?:[0-9]+\.?[0-9]*|\.[0-9]+)(?:[eE][+-]?[0-9]+)?").fullmatch
_isfinite = math.isfinite


def _numbers(words):
    """The floats `words` spell, or the first word that is not a finite ASCII decimal."""
    values = []
    for w in words:
        v = float(w) if _NUMBER(w) else math.nan
        if not _isfinite(v):
            return None, w
        values.append(v)
    return values, None


def _line(values, channels):
    """The model's `values` as one line of full-precision numbers, or None unless they are
    `channels` finite numbers."""
    values = list(values)
    if len(values) != channels or not all(map(_isfinite, values)):
        return None
    return " ".join(map(repr, values))


def _model_error(what, values, channels):
    return f"err {what}: the model gave {list(values)!r:.120}, not {channels} finite numbers\n"


def _read(model, channels, words):
    if len(words) != 1:
        return "err read takes no arguments\n"
    y = model.read()
    line = _line(y, channels)
    return _model_error("read", y, channels) if line is None else line + "\n"


def _write(model, channels, words):
    if len(words) != channels + 1:
        return f"err write needs {channels} number(s), got {len(words) - 1}\n"
    values, bad = _numbers(words[1:])
    if values is None:
        return f"err write: not a finite number: {bad[:40]!r}\n"
    a = model.write(values)
    line = _line(a, channels)
    return _model_error("write", a, channels) if line is None else "ok " + line + "\n"


def _advance(model, channels, words):
    values, _ = _numbers(words[1:]) if len(words) == 2 else (None, None)
    if values is None or not 0.0 <= values[0] <= MAX_ADVANCE:
        return f"err advance needs one finite duration in 0 ..= {MAX_ADVANCE:g} (s)\n"
    model.advance(values[0])
    return "ok\n"


_HANDLERS = {"read": _read, "write": _write, "advance": _advance}


def _skip_line(readline):
    """Read the rest of an over-long line; False if the input ended first."""
    while True:
        part = readline(MAX_LINE + 1)
        if not part:
            return False
        if part.endswith("\n"):
            return True


def serve(model, channels, stdin=None, stdout=None):
    """The request loop, until `stop` or the end of `stdin`; both end in the model's safe
    stop. Returns the exit status (0)."""
    if not 1 <= channels <= MAX_CHANNELS:
        raise ValueError(f"channels must be in 1 ..= {MAX_CHANNELS}, not {channels}")
    readline = (stdin or sys.stdin).readline
    write = (stdout or sys.stdout).write
    flush = (stdout or sys.stdout).flush
    handlers = _HANDLERS
    write(f"hello channels={channels}\n")
    flush()
    while True:
        line = readline(MAX_LINE + 1)
        if not line:  # EOF: the agent is gone
            model.safe_stop()
            return 0
        if len(line) > MAX_LINE and not line.endswith("\n"):
            if not _skip_line(readline):
                model.safe_stop()
                return 0
            answer = f"err request longer than {MAX_LINE} characters\n"
        else:
            words = line.split()
            verb = words[0] if words else ""
            if verb == "stop" and len(words) == 1:
                model.safe_stop()
                write("ok\n")
                flush()
                return 0
            handler = handlers.get(verb)
            if handler is not None:
                answer = handler(model, channels, words)
            elif verb == "stop":
                answer = "err stop takes no arguments\n"
            else:
                answer = f"err unknown request {line.strip()[:80]!r}\n"
        write(answer)
        flush()


def run(model, channels):
    """Serve `model` on this process's stdin/stdout; returns the exit status. Stray bytes
    on stdin become an `err`, and a broken stdout or Ctrl-C a safe stop, never a traceback."""
    sys.stdin.reconfigure(errors="replace")
    try:
        status = serve(model, channels)
    except (BrokenPipeError, KeyboardInterrupt):
        model.safe_stop()
        status = 0
    # Whatever happened to stdout, do not let the interpreter's final flush complain.
    try:
        sys.stdout.flush()
    except BrokenPipeError:
        pass
    os.dup2(os.open(os.devnull, os.O_WRONLY), sys.stdout.fileno())
    return status
