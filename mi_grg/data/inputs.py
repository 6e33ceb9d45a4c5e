"""Reading what a user hands over, within bounds: JSON and XML files that are too large or
too deeply nested are refused in one line naming the file, before a parser spends minutes
or gigabytes on them, and messages that embed a Python traceback (Mitsuba flattens a
plugin's into its own error) are reduced to the error itself; an exception from bad
input becomes one line naming the file and what was expected (``describe_error``,
``one_line``: the command line's error messages).
"""
from __future__ import annotations

import errno
import json
import re
import zipfile
from pathlib import Path

#: Bounds of the XML files we read (scenes, training configs). A scene's longest
#: attribute is a list of angles (~20 characters each).
MAX_XML_BYTES = 4 * 2 ** 20
MAX_XML_ELEMENTS = 10_000
MAX_XML_ATTRIBUTE = 2 ** 20
MAX_XML_DEPTH = 64
#: Bounds of the JSON files we read (meta_data.json, suites, metrics.json).
MAX_JSON_BYTES = 256 * 2 ** 20


class InputError(ValueError):
    """A file that is too large, too deep or not what it should be; the message names it."""


def _size(path: Path, limit: int, what: str) -> int:
    size = path.stat().st_size
    if size > limit:
        raise InputError(f"{path}: {size / 2 ** 20:.3g} MiB, above the {limit / 2 ** 20:.3g} "
                         f"MiB a {what} may have")
    return size


def read_json(path, what: str = "JSON file"):
    """The parsed content of ``path``. InputError (naming the file) for one above
    ``MAX_JSON_BYTES``, one that is not UTF-8 JSON, or one nested too deeply for Python."""
    path = Path(path)
    _size(path, MAX_JSON_BYTES, what)
    try:
        return json.loads(path.read_bytes())
    except (UnicodeDecodeError, json.JSONDecodeError) as e:
        raise InputError(f"{path}: not valid JSON ({e})") from None
    except RecursionError:
        raise InputError(f"{path}: nested too deeply to be a {what}") from None


def check_xml(path, what: str = "scene file") -> None:
    """InputError unless ``path`` is an XML file within ``MAX_XML_BYTES`` bytes,
    ``MAX_XML_ELEMENTS`` elements, ``MAX_XML_DEPTH`` levels and ``MAX_XML_ATTRIBUTE``
    characters per attribute (checked with a streaming parser that stops at the first
    excess)."""
    import xml.parsers.expat
    path = Path(path)
    _size(path, MAX_XML_BYTES, what)
    count, depth = [0], [0]

    def start(tag, attrs):
        count[0] += 1
        depth[0] += 1
        if count[0] > MAX_XML_ELEMENTS or depth[0] > MAX_XML_DEPTH:
            many = (f"more than {MAX_XML_ELEMENTS} elements" if count[0] > MAX_XML_ELEMENTS
                    else f"elements nested more than {MAX_XML_DEPTH} deep")
            raise InputError(f"{path}: {many}, above what a {what} may have")
        for name, value in attrs.items():
            if len(value) > MAX_XML_ATTRIBUTE or len(name) > MAX_XML_ATTRIBUTE:
                raise InputError(f"{path}: <{tag[:40]}> has an attribute of "
                                 f"{max(len(value), len(name))} characters, above the "
                                 f"{MAX_XML_ATTRIBUTE} a {what} may have")

    def end(tag):
        depth[0] -= 1

    parser = xml.parsers.expat.ParserCreate()
    parser.StartElementHandler, parser.EndElementHandler = start, end
    try:
        parser.Parse(path.read_bytes(), True)
    except xml.parsers.expat.ExpatError as e:
        raise InputError(f"{path}: not well-formed XML ({e})") from None
    except RecursionError:
        raise InputError(f"{path}: nested too deeply to be a {what}") from None


_FRAME = re.compile(r'File "[^"]*", line \d+, in \S+')
_ERROR_NAME = re.compile(r"\b[A-Za-z_][\w.]*(?:Error|Exception|Interrupt|Exit|Warning):")
_TRACEBACK = "Traceback (most recent call last):"


def without_traceback(text: str) -> str:
    """``text`` with any Python traceback inside it (flattened into one line, as Mitsuba
    embeds a plugin's, or not) reduced to the error itself, its last line."""
    text = str(text)
    start = text.find(_TRACEBACK)
    if start < 0:
        return text
    frames = list(_FRAME.finditer(text, start))
    rest = text[frames[-1].end():] if frames else text[start + len(_TRACEBACK):]
    error = _ERROR_NAME.search(rest)
    tail = rest[error.start():] if error else (rest.strip().splitlines() or [""])[-1]
    return " ".join(f"{text[:start]} {tail}".split())


#: Longest error line: a message quoting a huge value (an attribute, a key) is cut.
MAX_MESSAGE = 400


def one_line(message) -> str:
    """Bad input (our errors name the field or file): one line of at most MAX_MESSAGE
    characters, without any Python traceback a library embedded in it."""
    text = " ".join(without_traceback(str(message)).split())
    return text if len(text) <= MAX_MESSAGE else text[:MAX_MESSAGE - 4] + " ..."


_ERRNO_EXPECTED = {errno.ENOTDIR: "expected a directory there, found a file",
                   errno.EISDIR: "expected a file, found a directory",
                   errno.EACCES: "expected permission to read or write it",
                   errno.EPERM: "expected permission to read or write it",
                   errno.EROFS: "expected a writable file system",
                   errno.ENOSPC: "expected free disk space",
                   errno.ENOENT: "expected it to exist",
                   errno.EEXIST: "expected it not to exist yet"}


def _zip_file(e) -> str:
    """The file that zipfile was reading when it raised ``e`` (np.load of a .npz)."""
    tb, name = e.__traceback__, None
    while tb is not None:
        zf = tb.tb_frame.f_locals.get("self")
        if isinstance(zf, zipfile.ZipFile) and zf.filename:
            name = zf.filename
        tb = tb.tb_next
    return name or "a .npz file"


def describe_error(e) -> str:
    """One line for an exception from bad input: the file or option, and what was
    expected."""
    if isinstance(e, zipfile.BadZipFile):
        return f"{_zip_file(e)}: not a readable .npz archive ({e}; truncated?)"
    if isinstance(e, MemoryError):
        return f"out of memory ({e or 'MemoryError'}); use smaller sizes"
    if isinstance(e, OSError) and e.filename is not None:
        where = f"{e.filename}" + (f" -> {e.filename2}" if e.filename2 else "")
        why = _ERRNO_EXPECTED.get(e.errno, "")
        return f"{where}: {e.strerror or e}" + (f"; {why}" if why else "")
    if isinstance(e, EOFError):
        return f"a file ended too early ({e or 'EOFError'}; truncated?)"
    if isinstance(e, RecursionError):
        return "an input is nested too deeply to read (RecursionError)"
    return str(e)
