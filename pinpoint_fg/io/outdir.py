"""Output directories and files: the one place that decides whether ``--out`` may be written.

Rules (every subcommand that writes goes through :func:`prepare_output_dir`, :func:`prepare_output_file` or their
staged forms below, so a user's results are never replaced silently):

* ``--out`` naming an existing **file** (for a directory output), or a path **under** a file,
  is refused;
* an output directory that is one of the command's input directories, or lies inside one, is refused,
  with or without ``overwrite``;
* an existing **non-empty** directory is refused unless ``overwrite`` is true; then the command
  replaces the files it writes and leaves every other file in the directory alone (nothing is
  deleted wholesale: ``--out ~ --overwrite`` must not be able to empty a home directory);
* an output file that already exists is refused unless ``overwrite``; a directory in its place is
  always refused;
* a path the operating system cannot use (a NUL byte, a component longer than the file system
  allows, no permission) is refused, and so is a symbolic link that cannot be followed (a loop, or
  a missing target: writing through it would create a file elsewhere).

Every refusal is an :class:`~pinpoint_fg.errors.InputError` naming the path (one line, exit code 2
on the command line). The directory is created (with its parents) when the checks pass.

A command whose output is only of use whole (``simulate``, ``import-bop``, ``import-bag``: a run cut short would be
read as a shorter run) writes through :func:`staged_output_dir` instead: into a hidden sibling directory that is
moved into place at the end, and removed, with the parents it created, when the command fails (an out-of-memory
error, a corrupt input file met half-way, Ctrl-C). A SIGKILL or SIGTERM (whose default action runs no cleanup) can
leave the hidden sibling, never a half-written ``--out``.

A command whose output is one whole thing that ``--overwrite`` replaces whole (``export-bag``: a ROS 2 bag directory or
a ROS 1 bag file, which rosbags writes only new) writes through :func:`staged_replacement`: into a hidden sibling,
swapped for the old output only once it is complete, so a failure leaves the old output as it was; this is the
one ``--overwrite`` that removes files (the old bag's, which the new bag replaces whole). The command decides first
what at ``--out`` may be replaced (a bag, never a directory holding other files) and refuses an ``--out`` in its
input (:func:`check_not_an_input`). Replacing needs room for both for a moment.
"""

from __future__ import annotations

import os
import secrets
import shutil
import signal
import threading
from collections.abc import Iterator, Sequence
from contextlib import contextmanager
from pathlib import Path

from pinpoint_fg.errors import InputError

_SHOWN_ENTRIES = 3


def path_text(path: str | os.PathLike) -> str:
    """The path as text with control characters escaped (a NUL must not cut the message)."""
    text = os.fspath(path)
    text = text if isinstance(text, str) else text.decode("utf-8", "backslashreplace")
    return text.encode("unicode_escape").decode("ascii") if any(ord(c) < 32 for c in text) else text


def _usable(path: str | os.PathLike, what: str) -> Path:
    """``Path(path)`` after the checks that need no file system access (type, NUL byte)."""
    if isinstance(path, bytes):
        path = path.decode("utf-8", "surrogateescape")
    if not isinstance(path, str | os.PathLike):
        raise InputError(f"--out must be a path for the {what}, got {type(path).__name__}")
    text = os.fspath(path)
    if text == "":
        raise InputError(f"--out is empty; name a path for the {what}")
    if "\x00" in text:
        raise InputError("--out contains a NUL byte, which no path can hold", file=path_text(text))
    return Path(text)


def _file_ancestor(p: Path) -> Path | None:
    """The nearest existing ancestor of ``p`` when it is not a directory (so ``p`` cannot be created)."""
    for parent in p.absolute().parents:
        try:
            if parent.exists():
                return None if parent.is_dir() else parent
        except OSError:
            return None
    return None


def _os_problem(exc: OSError) -> str:
    return exc.strerror or type(exc).__name__


def _broken_link(p: Path) -> str | None:
    """Why the symbolic link ``p`` cannot be followed (a loop, a missing target), None when it can or is no link."""
    if not p.is_symlink():
        return None
    try:
        os.stat(p)
    except OSError as exc:
        return f"--out is a symbolic link that cannot be followed ({_os_problem(exc)})"
    return None


def shown_entries(names: Sequence[str]) -> str:
    """The first few of a directory's entry ``names`` for a one-line message (``a, b, c, ...``)."""
    return ", ".join(names[:_SHOWN_ENTRIES]) + (", ..." if len(names) > _SHOWN_ENTRIES else "")


def check_not_an_input(path: str | os.PathLike, inputs: Sequence[str | os.PathLike], what: str) -> None:
    """Refuse an output ``path`` that is one of the command's ``inputs`` or lies inside one (one line each)."""
    same = _same_dir(path, inputs)
    if same is not None:
        raise InputError(f"--out is also an input of this command; write the {what} to a directory of its own",
                         file=path_text(path))
    owner = _enclosing_input(path, inputs)
    if owner is not None:
        raise InputError(f"--out is inside the input {path_text(owner)}; the {what} would be mixed into that input's "
                         "files (and could replace one of them): choose an --out outside it", file=path_text(path))


def check_output_dir(path: str | os.PathLike, overwrite: bool, what: str,
                     inputs: Sequence[str | os.PathLike] = ()) -> Path:
    """The checks of :func:`prepare_output_dir` without creating anything (for commands that read and
    validate all their input first and must leave nothing behind when it is bad)."""
    check_not_an_input(path, inputs, what)
    p = _usable(path, what)
    try:
        if p.exists() or p.is_symlink():
            broken = _broken_link(p)
            if broken is not None:
                raise InputError(f"{broken}; choose another --out for the {what}", file=p)
            if not p.is_dir():
                raise InputError(f"--out exists and is a file, not a directory; choose another --out for the {what}",
                                 file=p)
            entries = sorted(e.name for e in os.scandir(p))
            if entries and not overwrite:
                shown = shown_entries(entries)
                raise InputError(
                    f"--out is not empty ({len(entries)} entries: {shown}); pass --overwrite to replace the {what} "
                    "in it, or choose another --out",
                    file=p,
                )
            return p
        blocker = _file_ancestor(p)
        if blocker is not None:
            raise InputError(f"--out cannot be created: {blocker} is a file, not a directory", file=p)
    except InputError:
        raise
    except OSError as exc:
        raise InputError(f"--out cannot be used for the {what}: {_os_problem(exc)}", file=path_text(p)) from None
    return p


def prepare_output_dir(path: str | os.PathLike, overwrite: bool, what: str,
                       inputs: Sequence[str | os.PathLike] = ()) -> Path:
    """Check that ``path`` may receive the output ``what`` (e.g. ``"result"``), create it, return it.

    Raises :class:`InputError` (module docstring) for a file in the way, a path under a file, a
    non-empty directory without ``overwrite``, or a path the OS refuses; and, with or without
    ``overwrite``, for a path that is one of the command's input directories ``inputs`` or lies inside one (a
    result written into its own recording or its ``masks``, or an evaluation into a result it reads, would mix
    two directories' files).
    """
    p = check_output_dir(path, overwrite, what, inputs)
    try:
        p.mkdir(parents=True, exist_ok=True)
    except OSError as exc:
        raise InputError(f"--out cannot be used for the {what}: {_os_problem(exc)}", file=path_text(p)) from None
    return p


def _same_dir(path: str | os.PathLike, inputs: Sequence[str | os.PathLike]) -> str | os.PathLike | None:
    """The input of ``inputs`` that is the same existing directory as ``path`` (links followed), or None."""
    try:
        if not os.path.isdir(path):
            return None
        for root in inputs:
            if os.path.isdir(root) and os.path.samefile(path, root):
                return root
    except (OSError, ValueError, TypeError):
        return None  # unusable paths are refused, with their own message, by the checks that follow
    return None


def _enclosing_input(path: str | os.PathLike, inputs: Sequence[str | os.PathLike]) -> str | os.PathLike | None:
    """The input directory of ``inputs`` that ``path`` lies inside (at any depth, links followed), or None.

    Decision: an output directory inside an input (``track RUN --out RUN/masks``, ``batch RUN --out RUN/results``)
    is refused like the input itself, with or without ``--overwrite``: a result file there replaced a namesake of
    the input (a mask named ``result.json``) or left files the input's readers then met as part of it.
    """
    try:
        real = Path(os.path.realpath(path))  # not Path.resolve: a symlink loop was its RuntimeError traceback
        for root in inputs:
            if os.path.isdir(root) and Path(os.path.realpath(root)) in real.parents:
                return root
    except (OSError, ValueError, TypeError):
        return None  # unusable paths are refused, with their own message, by the checks that follow
    return None


#: Files a run or a result consists of, and the directories of a run's PNGs: an output file there replaced (with
#: ``--overwrite``) or added to the command's own input (``calibrate-spread RES --out RES/result.json``, exit 0).
_INPUT_FILE_NAMES = frozenset({"recording.json", "frames.csv", "result.json", "estimates.csv", "particles.npz",
                               "particles.journal", "trajectory.tum", "smoothed.csv", "modes.csv"})
_INPUT_FILE_DIRS = frozenset({"masks", "images"})


def _input_file(p: Path, inputs: Sequence[str | os.PathLike]) -> Path | None:
    """The input directory of which ``p`` would be (or replace) one of the files it consists of, or None."""
    real = Path(os.path.realpath(p))
    for root in inputs:
        base = Path(os.path.realpath(root))
        if base in real.parents:
            inner = real.relative_to(base).parts
            if real.name in _INPUT_FILE_NAMES or _INPUT_FILE_DIRS.intersection(inner[:-1]):
                return Path(root)
    return None


def prepare_output_file(path: str | os.PathLike, overwrite: bool, what: str,
                        inputs: Sequence[str | os.PathLike] = ()) -> Path:
    """Check that the file ``path`` may receive ``what``; create its parent directory; return it.

    Refuses an existing file without ``overwrite``, a directory in its place, a parent that is a
    file, and paths the OS refuses (:class:`InputError`). The file itself is not created.
    ``inputs``: the command's input directories (runs, results); a ``path`` that is one of their files
    (``recording.json``, ``result.json``, a mask, ...) is refused, with or without ``overwrite``.
    """
    p = _usable(path, what)
    owner = _input_file(p, inputs)
    if owner is not None:
        raise InputError(f"--out is a file of the input {owner}; writing the {what} there would replace or corrupt "
                         "that input: choose another --out", file=p)
    try:
        if p.is_dir():
            raise InputError(f"--out is a directory; name a file for the {what}", file=p)
        if p.exists() or p.is_symlink():
            broken = _broken_link(p)  # a loop was an OSError traceback when writing, after the work
            if broken is not None:
                raise InputError(f"{broken}; choose another --out for the {what}", file=p)
            if not overwrite:
                raise InputError(f"--out exists; pass --overwrite to replace the {what}, or choose another --out",
                                 file=p)
            return p
        blocker = _file_ancestor(p)
        if blocker is not None:
            raise InputError(f"--out cannot be created: {blocker} is a file, not a directory", file=p)
        p.parent.mkdir(parents=True, exist_ok=True)
        # the file name itself must be acceptable too (length limits): probe without creating it
        os.stat(p.parent)
        if len(os.fsencode(p.name)) > os.pathconf(p.parent, "PC_NAME_MAX"):
            raise OSError(36, "File name too long")
    except InputError:
        raise
    except (OSError, ValueError) as exc:
        why = _os_problem(exc) if isinstance(exc, OSError) else str(exc)
        raise InputError(f"--out cannot be used for the {what}: {why}", file=path_text(p)) from None
    return p


@contextmanager
def staged_output_dir(path: str | os.PathLike, overwrite: bool, what: str,
                      inputs: Sequence[str | os.PathLike] = ()) -> Iterator[Path]:
    """Yield a new hidden sibling directory of ``path`` to write the output ``what`` into; on success move its files
    into ``path``, on any exception remove it and the parents of ``path`` it created (module docstring).

    ``path`` is checked as by :func:`prepare_output_dir` (not created until the end). When it exists (empty, or with
    ``overwrite``) the written files replace their namesakes in it and every other file is left alone, as before;
    otherwise the sibling is renamed to ``path``. An :class:`InputError` or ``OSError`` naming a file in the sibling
    is re-raised naming that file under ``path``.
    """
    out = check_output_dir(path, overwrite, what, inputs)
    created = missing_dirs(out.parent)
    stage = _new_stage(out, what, created)
    try:
        yield stage
        _publish(stage, out)
    except BaseException as exc:
        _abandon_stage(exc, stage, created, stage, out)
        raise


@contextmanager
def staged_replacement(path: str | os.PathLike, what: str) -> Iterator[Path]:
    """Yield a path at which to write the output ``what`` (a file or a directory, created by the writer) inside a
    new hidden sibling directory of ``path``, under ``path``'s own name; on success swap it in for what is at
    ``path``; on any exception before the swap remove the sibling (and the parents of ``path`` it created) and leave
    ``path`` as it was.

    The caller has checked that what is at ``path`` may be replaced (nothing of the user's but the old output). A
    file is replaced by one ``os.replace``. A directory is moved into the sibling and the new output into its place,
    with SIGINT and SIGTERM held back between the two moves (a Ctrl-C there takes effect once both are done); when
    the second move fails the old output is moved back, and when that fails too it is left in the sibling, which the
    one-line error names: the old output is never deleted before the new one is in place (and is deleted, with the
    sibling, before a held signal takes effect). A SIGTERM while the new output is written leaves the sibling with
    its half (the old output untouched), as a SIGKILL does; a SIGKILL between the two moves leaves the old output in
    the sibling. ``path`` is taken as absolute first (``.`` has no name to stage under).
    """
    path = Path(os.path.abspath(path))
    created = missing_dirs(path.parent)
    stage = _new_stage(path, what, created)
    new = stage / path.name
    try:
        yield new
    except BaseException as exc:
        _abandon_stage(exc, stage, created, new, path)
        raise
    with _signals_held():
        _swap_in(new, path, stage, what)
        shutil.rmtree(stage, ignore_errors=True)  # the old output, once the new one is in place


def _new_stage(path: Path, what: str, created: list[Path]) -> Path:
    """A new hidden sibling directory of ``path`` to stage the output ``what`` in (``created``: the parents of
    ``path`` made for it, removed again when it cannot be made)."""
    try:
        path.parent.mkdir(parents=True, exist_ok=True)
        stage = path.parent / f".{path.name[:100]}.partial-{os.getpid()}-{secrets.token_hex(4)}"
        stage.mkdir()
    except OSError as exc:
        remove_empty_dirs(created)
        raise InputError(f"--out cannot be used for the {what}: {_os_problem(exc)}", file=path_text(path)) from None
    return stage


def _abandon_stage(exc: BaseException, stage: Path, created: list[Path], written: Path, out: Path) -> None:
    """After a failed write: remove the hidden ``stage`` and the parents made for it, and let ``exc`` name ``out``
    where it named ``written`` (the output inside the stage: :func:`_rename_staged`)."""
    shutil.rmtree(stage, ignore_errors=True)
    remove_empty_dirs(created)
    if isinstance(exc, InputError | OSError):
        _rename_staged(exc, written, out)


def _swap_in(new: Path, path: Path, stage: Path, what: str) -> None:
    """Put ``new`` at ``path`` (:func:`staged_replacement`): one ``os.replace`` for a file; for a directory, the
    old one moved into ``stage`` first and back when the new one cannot take its place."""
    if not (path.is_dir() and not path.is_symlink()):
        try:
            os.replace(new, path)
        except OSError as exc:
            shutil.rmtree(stage, ignore_errors=True)
            raise InputError(f"cannot replace --out with the new {what}: {_os_problem(exc)}", file=path) from None
        return
    old = stage / f".old-{secrets.token_hex(4)}"
    try:
        os.rename(path, old)
    except OSError as exc:
        shutil.rmtree(stage, ignore_errors=True)
        raise InputError(f"cannot move the old {what} aside to replace it: {_os_problem(exc)}", file=path) from None
    try:
        os.rename(new, path)
    except OSError as exc:
        why = _os_problem(exc)
        try:
            os.rename(old, path)
        except OSError:
            raise InputError(f"cannot move the new {what} into place ({why}) nor the old one back; the old {what} "
                             f"is kept at {old}", file=path) from None
        shutil.rmtree(stage, ignore_errors=True)
        raise InputError(f"cannot move the new {what} into place: {why}; the old {what} is as it was",
                         file=path) from None


@contextmanager
def _signals_held() -> Iterator[None]:
    """Hold SIGINT and SIGTERM back while the block runs: a signal that arrives meanwhile is handed to its own
    handler right after the block (Ctrl-C's KeyboardInterrupt, SIGTERM's default exit). Python runs signal handlers
    in the main thread whichever thread the kernel delivers to, so the handlers are swapped, not the thread's signal
    mask; outside the main thread (where handlers cannot be set) the block runs as it is."""
    if threading.current_thread() is not threading.main_thread():
        yield
        return
    caught: list[int] = []
    held = (signal.SIGINT, signal.SIGTERM)
    previous = {s: signal.signal(s, lambda signum, frame: caught.append(signum)) for s in held}
    try:
        yield
    finally:
        for s, handler in previous.items():
            signal.signal(s, handler)
        for s in dict.fromkeys(caught):
            handler = previous[s]
            if callable(handler):
                handler(s, None)
            elif handler == signal.SIG_DFL:
                signal.raise_signal(s)


def _publish(stage: Path, out: Path) -> None:
    """Move the staged output into ``out``: a rename when ``out`` does not exist, else file by file (replacing)."""
    if not (out.exists() or out.is_symlink()):
        os.rename(stage, out)
        return
    for src in sorted(stage.rglob("*")):
        if src.is_dir():
            continue
        dest = out / src.relative_to(stage)
        dest.parent.mkdir(parents=True, exist_ok=True)
        os.replace(src, dest)
    shutil.rmtree(stage, ignore_errors=True)


def missing_dirs(path: str | os.PathLike) -> list[Path]:
    """``path`` and those of its parents that do not exist yet, deepest first: what creating ``path`` creates, for
    :func:`remove_empty_dirs` when the command then fails. Empty for a path that cannot be inspected (refused, with
    its own message, by :func:`prepare_output_dir`)."""
    try:
        p = Path(os.fspath(path)).absolute()
        missing = []
        for d in (p, *p.parents):
            if d.exists() or d.is_symlink():
                break
            missing.append(d)
        return missing
    except (OSError, ValueError, TypeError):
        return []


def remove_empty_dirs(dirs: Sequence[Path]) -> None:
    """Remove ``dirs`` (directories a command created, deepest first) that are still empty; stop at the first that
    is not (it holds files the user should see, e.g. a result cut short)."""
    for d in dirs:
        try:
            d.rmdir()
        except OSError:
            return


def _rename_staged(exc: InputError | OSError, stage: Path, out: Path) -> None:
    """Name ``out`` instead of the removed staging directory in ``exc``'s file (the file as the user will know it)."""
    name = exc.file if isinstance(exc, InputError) else exc.filename
    if not isinstance(name, str) or not name.startswith(str(stage)):
        return
    renamed = str(out) + name[len(str(stage)):]
    if isinstance(exc, InputError):
        exc.__init__(exc.reason, file=renamed, row=exc.row, column=exc.column)  # type: ignore[misc]
    else:
        exc.filename = renamed
