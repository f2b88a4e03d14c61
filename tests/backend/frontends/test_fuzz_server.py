"""Property-based fuzzing of the ``genre serve`` protocol (issue 18), with Hypothesis.

One server process (the tiny trained weights of conftest's ``trained``), started in a
temporary working folder, receives generated lines: every request type of
``docs/protocol.md`` with every field drawn from plain values and from
arbitrary JSON (NaN and infinities, integers of 4,000 and of more than 4,300
digits, lone surrogates, NUL, nesting up to 3,000 deep, strings up to 200,000
characters), sent as ASCII escapes or as raw UTF-8 (where a lone surrogate
becomes bytes that are not UTF-8), and lines that are not JSON at all (any
bytes, cut-off requests, blank lines).  Paths point at the real photo and
mask, at folders that exist or not, at names that are too long or not UTF-8,
at a FIFO, ``/dev/null``, symbolic links and the inputs themselves.

After every line the server must answer ``ping``; every stdout line must be
one ASCII JSON object with a documented event type and, for an error, a
documented code (never ``internal``) and a one-line capped message; the
answer must be the one the protocol document prescribes (the oracle below
reads each line as the server does and applies the documented rules).  After
every example (its jobs finished) the only entries created, changed or
removed in the temporary tree are the outputs and intermediates folders of
the requests the server had to accept; every accepted job ends exactly once,
a result names its requested output and a cancelled job writes nothing.

Reproducible: derandomised (the same examples on every run, no example
database) with a bounded number of examples (``GENRE_FUZZ_EXAMPLES``, default
400; raise it for a longer local hunt: 800 took 294 s of the suite's 18.8 minutes on a 2-core AVX2 EPYC).
Known bad lines (``REGRESSIONS``) run first on every run.
"""

from __future__ import annotations

import collections
import json
import math
import os
import re
import shutil
import threading
import time
from dataclasses import dataclass, field
from pathlib import Path, PurePosixPath

import pytest
from hypothesis import HealthCheck, assume, example, given, note, settings
from hypothesis import strategies as st

from genre_backend.inference.options import OPTIONS, QUALITIES
from genre_backend.atomic import is_temporary_name
from support.server import ServerProcess

EXAMPLES = int(os.environ.get("GENRE_FUZZ_EXAMPLES", "400"))
EVENT_TYPES = {"pong", "version", "progress", "result", "error", "cancelled", "bye"}
ERROR_CODES = {"bad_json", "unknown_type", "missing_field", "bad_field", "bad_image", "bad_mask", "no_object",
               "output_unwritable", "bad_weights", "unknown_job", "internal"}
JOB_CODES = {"bad_image", "bad_mask", "no_object", "output_unwritable"}  # how an accepted job may fail
DIRECT_CODES = {"bad_json", "unknown_type", "missing_field", "bad_field", "unknown_job", "internal"}  # answers to the line itself
STAGES = ["load", "preprocess", "depth", "partial_sph", "inpaint", "voxels", "refine", "mesh", "write"]
# every option the server accepts: the mesh options' record (genre_backend/inference/options.py), the named set `quality`
# and the intermediates folder; each drawn below, the record's ones from their own kind and range
RECORD = {o.name: o for o in OPTIONS}
OPTION_KEYS = (*RECORD, "quality", "save_intermediates")
MAX_MESSAGE = 2100  # the server's 2,000-character cap plus its "… (N characters)" tail


# ---- lines the JSON encoder cannot write ---------------------------------------------------------------
class Raw(str):
    """JSON text put into a line as it is: a 6,000-digit integer, 3,000-deep nesting, ``1e400``."""


def encode(value, ascii_: bool) -> str:
    """``value`` as JSON text; :class:`Raw` parts verbatim; ``ascii_`` False leaves non-ASCII (and lone surrogates) raw."""
    if isinstance(value, Raw):
        return str(value)
    if isinstance(value, dict):
        return "{" + ", ".join(f"{encode(k, ascii_)}: {encode(v, ascii_)}" for k, v in value.items()) + "}"
    if isinstance(value, list):
        return "[" + ", ".join(encode(v, ascii_) for v in value) + "]"
    return json.dumps(value, ensure_ascii=ascii_)  # (NaN and ±Infinity as Python's reader takes them)


def to_line(value, ascii_: bool) -> bytes:
    """One request line as bytes (a lone surrogate sent raw becomes the bytes a careless encoder writes)."""
    line = encode(value, ascii_).encode("utf-8", "surrogatepass")
    assert b"\n" not in line  # JSON escapes newlines; one request is one line
    return line


def _nest(depth: int, kind: str) -> Raw:
    return Raw("[" * depth + "]" * depth if kind == "[" else '{"k": ' * depth + "0" + "}" * depth)


def _huge(digits: int, negative: bool) -> Raw:
    return Raw(("-" if negative else "") + "1" + "7" * (digits - 1))


# ---- strategies -------------------------------------------------------------------------------------------
CHARS = st.one_of(
    st.characters(codec="utf-8"),
    st.characters(min_codepoint=0xD800, max_codepoint=0xDFFF, exclude_categories=()),  # lone surrogates
    st.sampled_from(list("\x00\n\r\t\"\\/.\u2028\x85\ufeff\x7f é")),
)
TEXT = st.text(CHARS, max_size=16)
LONG = st.builds(lambda unit, n: unit * n, st.sampled_from(["x", "é", "/", "../", "\x00", "\ud800", "\udce9", "😀", " "]),
                 st.integers(1_000, 200_000))
HUGE = st.builds(_huge, st.one_of(st.integers(20, 400), st.sampled_from([4_000, 4_300, 4_301]), st.integers(4_302, 6_000)), st.booleans())
NESTED = st.builds(_nest, st.one_of(st.integers(2, 60), st.integers(2, 60), st.integers(950, 1_010), st.integers(1_011, 3_000)), st.sampled_from("[{"))
ODD_NUMBERS = st.sampled_from([Raw(t) for t in ("1e400", "-1e400", "1E-400", "-0", "0.5e0", "4.9e-324", "1e308", "0.99999999999999999")])
SCALARS = st.one_of(st.none(), st.booleans(), st.integers(), st.floats(), TEXT, LONG, HUGE, ODD_NUMBERS)
CONTAINERS = st.recursive(SCALARS, lambda c: st.lists(c, max_size=3) | st.dictionaries(TEXT, c, max_size=3), max_leaves=6)
JSON = st.one_of(SCALARS, SCALARS, SCALARS, CONTAINERS, CONTAINERS, NESTED)  # (one_of picks its branches about evenly)
NOT_A_STRING = JSON.filter(lambda v: not isinstance(v, str) or isinstance(v, Raw))
OMIT = object()  # a field left out
VALID_ID = st.one_of(TEXT, st.integers(), st.floats(allow_nan=False, allow_infinity=False), st.builds(_huge, st.just(4_000), st.booleans()))
INVALID_ID = st.one_of(st.sampled_from([True, False, None, [], {}, Raw("NaN"), Raw("Infinity"), Raw("1e400")]),
                       JSON.filter(lambda v: isinstance(v, (bool, list, dict)) or v is None))
ANY = st.one_of(JSON, HUGE, TEXT, LONG, st.just(OMIT))
PARTS = ["id", "image", "output", "mask", "options", *OPTION_KEYS, "unknown_option", "extra"]


def fitting(spec):
    """Values the record says ``spec`` takes (and ``None``, not given): its ends, the inside of its range, its choices."""
    if spec.kind == "bool":
        return st.sampled_from([True, False, None])
    if spec.kind == "choice":
        return st.sampled_from([*spec.choices, None])
    ends = [v for v, open_ in ((spec.lo, spec.lo_open), (spec.hi, spec.hi_open)) if not open_]
    if spec.kind == "int":
        return st.one_of(st.integers(int(spec.lo), int(spec.hi)), st.sampled_from([*map(int, ends), None]))
    inside = st.floats(spec.lo, spec.hi, exclude_min=spec.lo_open, exclude_max=spec.hi_open)
    near = [spec.lo + 1e-9 if spec.lo_open else spec.lo, spec.hi - 1e-9 if spec.hi_open else spec.hi]
    return st.one_of(inside, st.sampled_from([*near, *[int(e) for e in ends if float(e).is_integer()], 5e-324 + spec.lo, None]))


def unfitting(spec):
    """Odd values for ``spec``: anything JSON, the wrong kind, just outside its range, NaN and overflowing numbers."""
    odd = [True, "1", [], {}, Raw("NaN"), Raw("1e400"), Raw("-1e400")]
    if spec.kind == "choice":
        odd += [c.upper() for c in spec.choices] + [c + " " for c in spec.choices] + [c + "\x00" for c in spec.choices] + [""]
    elif spec.kind == "bool":
        odd += [0, 1, "true"]
    else:
        odd += [spec.lo, spec.hi, spec.lo - 1, spec.hi + 1, spec.lo - 1e-4, spec.hi + 1e-4, -0.0, float(spec.hi), float(spec.lo) + 0.5]
    return st.one_of(JSON, HUGE, st.sampled_from(odd))


def takes(spec, value) -> bool:
    """Whether the protocol document's rules for ``spec``'s kind and range accept ``value`` (``None``: not given)."""
    if value is None:
        return True
    if spec.kind == "bool":
        return isinstance(value, bool)
    if spec.kind == "choice":
        return isinstance(value, str) and value in spec.choices
    if isinstance(value, bool) or not isinstance(value, int if spec.kind == "int" else (int, float)):
        return False
    above = spec.lo < value if spec.lo_open else spec.lo <= value
    below = value < spec.hi if spec.hi_open else value <= spec.hi
    return above and below


@dataclass(frozen=True)
class Tree:
    """The temporary tree: ``root/work`` is the server's working folder; ``root/inputs`` holds the photo and its mask."""

    root: Path

    @property
    def work(self) -> Path:
        return self.root / "work"

    @property
    def inputs(self) -> Path:
        return self.root / "inputs"


ROOT = "@ROOT@"  # the tree's absolute path in a generated line: put in just before the line is sent


def _example_strategy():
    """The lines of one example (1 to 3 of them)."""
    tree = Tree(Path(ROOT))
    photo, mask = str(tree.inputs / "photo.png"), str(tree.inputs / "mask.png")
    names = st.one_of(
        st.sampled_from(["mesh.obj", "a.ply", "b.glb", "c.stl", "noext", ".hidden", "UPPER.OBJ", "café.obj", "space name.obj",
                         "tab\t.obj", "nl\n.obj", "\u2028.ply", "-", "n" * 250 + ".obj", "n" * 300 + ".obj",
                         os.fsdecode(b"caf\xe9.obj"), os.fsdecode(b"\xff\xfe.glb")]),
        st.text(st.one_of(st.characters(codec="utf-8", exclude_characters="/\x00"),
                          st.characters(min_codepoint=0xDC80, max_codepoint=0xDCFF, exclude_categories=())),  # non-UTF-8 bytes of a name
                min_size=1, max_size=12).filter(lambda s: s not in (".", "..")),
    )
    folders = st.sampled_from(["", "sub/", "sub/deeper/", "./", "sub/../", "new/", "new/deeper/", "missing/x/", "../out/", "../work/sub/",
                               f"{tree.work}/", f"{tree.root}/out/", f"{tree.root}//out/./"])
    confined = st.builds(lambda d, n: d + n, folders, names)  # paths inside the tree
    special_out = st.sampled_from([photo, mask, "../inputs/photo.png", "../inputs/mask.png", "/dev/null", "fifo", ".", "..", "sub", "sub/", "",
                                   "link.obj", "dangling.obj", "existing.obj", "../out/", "/", "missing/x.obj", str(tree.work)])
    special_in = st.sampled_from([photo, mask, "../inputs/photo.png", "fifo", "/dev/zero", "/dev/null", ".", "sub", "", "existing.obj",
                                  "link.obj", "dangling.obj", "../inputs/absent.png", "n" * 300 + ".png"])
    image_field = st.one_of(ANY, special_in, confined)
    folder_field = st.one_of(st.just(OMIT), st.none(), confined, st.sampled_from([".", "sub", "sub/deeper", "../out", "../inputs", "fifo",
                                                                                  "existing.obj", "/dev/null", "n" * 300]))

    @st.composite
    def reconstruct(draw, ids):
        """A request the server must accept, with 0 to 3 of its parts then replaced by odd values."""
        n = draw(st.sampled_from([0, 0, 1, 1, 1, 1, 2, 3]))
        broken = set(draw(st.lists(st.sampled_from(PARTS), min_size=n, max_size=n, unique=True)))
        real = "image" not in broken and draw(st.integers(0, 3)) > 0
        msg = {"type": "reconstruct", "id": draw(st.sampled_from(ids))}
        if real:
            msg["image"] = draw(st.sampled_from([photo, "../inputs/photo.png"]))
        else:  # a path that names no image (or, broken, anything at all)
            msg["image"] = draw(image_field if "image" in broken else confined)
        msg["output"] = draw(st.one_of(confined, confined, confined, special_out))
        msg["mask"] = draw(st.sampled_from([OMIT, None, mask, mask]))
        opts = {}
        for name, spec in RECORD.items():  # every mesh option, by its kind and range
            if draw(st.integers(0, 2)) == 0:
                opts[name] = draw(fitting(spec))
        if draw(st.integers(0, 3)) == 0:
            opts["quality"] = draw(st.sampled_from([*QUALITIES, None]))
        if draw(st.integers(0, 3)) == 0:
            opts["save_intermediates"] = draw(folder_field)
        if "id" in broken:
            msg["id"] = draw(st.one_of(VALID_ID, INVALID_ID, st.just(OMIT)))
        if "output" in broken:
            msg["output"] = draw(st.one_of(ANY, special_out))
        if "mask" in broken:
            msg["mask"] = draw(st.one_of(ANY, special_in, st.just(photo)))
        for name, spec in RECORD.items():
            if name in broken:
                opts[name] = draw(unfitting(spec))
        if "quality" in broken:
            opts["quality"] = draw(st.one_of(JSON, st.sampled_from(["Fast", "best ", "", "slow", 1, True, "fast\x00"])))
        if "save_intermediates" in broken:
            opts["save_intermediates"] = draw(st.one_of(folder_field, ANY))
        if "unknown_option" in broken:
            opts[draw(TEXT)] = draw(JSON)
        msg["options"] = {k: v for k, v in opts.items() if v is not OMIT}
        if not msg["options"] and draw(st.booleans()):
            msg["options"] = OMIT
        if "options" in broken:
            msg["options"] = draw(st.one_of(NOT_A_STRING, TEXT, st.sampled_from([False, 0, "", [], None, [{}]]), st.just(OMIT)))
        if "extra" in broken:
            for k, v in draw(st.dictionaries(st.one_of(TEXT, st.sampled_from(["extra", "id", "type", "image", "output", "mask"])), ANY,
                                             min_size=1, max_size=2)).items():
                msg[k] = v  # unknown top-level fields, or a field given a second, odd value
        return {k: v for k, v in msg.items() if v is not OMIT}

    @st.composite
    def request(draw, ids):
        kind = draw(st.sampled_from(["ping", "version", "reconstruct", "reconstruct", "reconstruct", "reconstruct", "cancel", "shutdown", "other"]))
        if kind == "reconstruct":
            return draw(reconstruct(ids))
        msg: dict = {}
        if kind == "other":
            msg["type"] = draw(st.one_of(JSON, TEXT, st.sampled_from(["Ping", "ping ", "reconstruct\x00", "RECONSTRUCT", "bye"]), st.just(OMIT)))
        else:
            msg["type"] = kind
        if kind == "shutdown":  # a shutdown that the server accepts would end the one server: its id is always refused
            msg["id"] = draw(INVALID_ID)
        elif kind == "cancel":
            msg["id"] = draw(st.one_of(st.sampled_from(ids), st.sampled_from(ids), VALID_ID, INVALID_ID, st.just(OMIT)))
        else:
            msg["id"] = draw(st.one_of(VALID_ID, VALID_ID, INVALID_ID, st.just(OMIT)))
        if draw(st.integers(0, 4)) == 0:
            for k, v in draw(st.dictionaries(st.one_of(TEXT, st.sampled_from(["extra", "id", "type"])), ANY, max_size=2)).items():
                msg[k] = v
        return {k: v for k, v in msg.items() if v is not OMIT}

    @st.composite
    def line(draw, ids):
        form = draw(st.sampled_from(["request"] * 12 + ["json", "bytes", "blank", "cut"]))
        if form == "json":
            return to_line(draw(JSON), draw(st.booleans()))
        if form == "bytes":
            return draw(st.binary(max_size=120)).replace(b"\n", b"")
        if form == "blank":
            return draw(st.sampled_from([b"", b"   ", b"\t\r", "\u2028".encode(), "\u00a0".encode()]))
        whole = to_line(draw(request(ids)), draw(st.booleans()))
        if form == "cut":
            return whole[: draw(st.integers(0, max(0, len(whole) - 1)))]
        return whole

    @st.composite
    def example(draw):
        ids = draw(st.lists(VALID_ID, min_size=1, max_size=3, unique_by=lambda v: encode(v, True)))
        return draw(st.lists(line(ids), min_size=1, max_size=3))

    return example()


EXAMPLE = _example_strategy()


# ---- the oracle: what the protocol document says the answer is --------------------------------------------
BLANK, NOT_JSON, UNSURE = object(), object(), object()


def _depth(text: str) -> int:
    """The deepest nesting of brackets in JSON text (outside strings)."""
    depth = best = 0
    for ch in re.findall(r"[\[\]{}]", re.sub(r'"(?:[^"\\]|\\.)*"', "", text)):
        depth += 1 if ch in "[{" else -1
        best = max(best, depth)
    return best


def as_the_server_reads(line: bytes):
    """The message the server makes of ``line``: BLANK, NOT_JSON, UNSURE (nesting near the recursion limit), or the value."""
    text = line.decode("utf-8", "replace").strip()
    if not text:
        return BLANK
    depth = _depth(text)
    if depth > 1_100:
        return NOT_JSON  # deeper than Python's recursion limit (1,000) lets its reader go
    if depth >= 900:
        return UNSURE  # whether it parses depends on the reader's own stack depth
    out: list = []

    def parse():  # on a fresh thread: a shallow stack like the server's, not pytest's and Hypothesis's
        try:
            out.append(json.loads(text))
        except (ValueError, RecursionError):
            out.append(NOT_JSON)

    t = threading.Thread(target=parse)
    t.start()
    t.join()
    return out[0]


def key(value) -> str:
    return json.dumps(value)


def valid_id(value) -> bool:
    return not isinstance(value, bool) and isinstance(value, (str, int, float)) and (not isinstance(value, float) or math.isfinite(value))


def usable_path(value) -> bool:
    """A non-empty string some file could have as its name (no NUL; lone surrogates only as escaped bytes)."""
    if not isinstance(value, str) or not value or "\x00" in value:
        return False
    try:
        os.fsencode(value)
    except UnicodeEncodeError:
        return False
    return True


def refusals(msg: dict) -> set[str]:
    """The error codes the document gives a ``reconstruct`` with a valid id: empty if it must be accepted."""
    codes = set()
    for name, required in (("image", True), ("output", True), ("mask", False)):
        value = msg.get(name)
        if value is None:
            if required:
                codes.add("missing_field")
        elif not usable_path(value):
            codes.add("bad_field")
    opts = msg.get("options")
    if opts is not None:
        if not isinstance(opts, dict):
            return codes | {"bad_field"}
        f, s, up, quality = (opts.get(k) for k in ("format", "save_intermediates", "up", "quality"))
        if set(opts) - set(OPTION_KEYS):
            codes.add("bad_field")
        if not all(takes(spec, opts.get(name)) for name, spec in RECORD.items()):
            codes.add("bad_field")
        if quality is not None and not (isinstance(quality, str) and quality in QUALITIES):
            codes.add("bad_field")
        output = msg.get("output")
        ext = PurePosixPath(output).suffix.lower().lstrip(".") if usable_path(output) else None
        if f in ("obj", "ply", "glb") and ext in ("obj", "ply", "glb") and ext != f:  # format and extension must agree
            codes.add("bad_field")
        if up == "z":
            written = f if f in ("obj", "ply", "glb") else (ext if ext in ("obj", "ply", "glb") else "obj")
            if written != "ply":  # up z is for ply only
                codes.add("bad_field")
        if s is not None and not usable_path(s):
            codes.add("bad_field")
    return codes


def written_files(output: str, fmt, texture) -> list[str]:
    """The files a job writes, as docs/protocol.md says: the mesh, and with ``texture`` an OBJ's .mtl and _texture.png."""
    if fmt is None:
        ext = PurePosixPath(output).suffix.lower().lstrip(".")
        fmt = ext if ext in ("obj", "ply", "glb") else "obj"
    if texture is True and fmt == "obj" and PurePosixPath(output).name:
        p = PurePosixPath(output)
        return [output, str(p.with_suffix(".mtl")), str(p.with_name(p.stem + "_texture.png"))]
    return [output]


def job_failure(ev: dict, job: dict) -> bool:
    """Whether ``ev`` is the error an accepted job ends with: a JOB_CODES error, or (the tiny weights predict the shell
    target) the job's own bad_field for visible_fusion or pit sealing, told from a refusal by its message."""
    if ev["type"] != "error":
        return False
    if ev["code"] in JOB_CODES:
        return True
    return job["shell_only"] and ev["code"] == "bad_field" and ev["message"].startswith(("visible_fusion:", "pit_sealing:"))


@dataclass
class Expected:
    """What one line must get: ``answer`` (type, codes, id) among the events of its window, or None; an accepted job."""

    answer: tuple | None = None
    job: dict | None = None  # {"key", "id", "image", "output", "intermediates"} of a reconstruct the server must queue
    cancel: str | None = None  # the key a cancel names
    answers: tuple[int, int] = (1, 1)  # how many direct answers (pong, version, refusals) the line gets, at least and at most
    unsure: bool = False  # nesting near the recursion limit: read or refused, with whatever id it has


def expect(msg) -> Expected:
    if msg is BLANK:
        return Expected(answers=(0, 0))
    if msg is UNSURE:
        return Expected(answers=(0, 1), unsure=True)
    if msg is NOT_JSON or not isinstance(msg, dict):
        return Expected(("error", {"bad_json"}, None))
    if "id" in msg and not valid_id(msg["id"]):
        return Expected(("error", {"bad_field"}, None))
    rid = msg.get("id")
    if "type" not in msg:
        return Expected(("error", {"missing_field"}, rid))
    kind = msg["type"]
    if kind in ("ping", "version"):
        return Expected(("pong" if kind == "ping" else "version", None, rid))
    if kind == "reconstruct":
        if "id" not in msg:
            return Expected(("error", {"missing_field"}, None))
        codes = refusals(msg)
        if codes:
            return Expected(("error", codes, rid))
        opts = msg.get("options") or {}
        # the tiny weights predict the shell target: visible_fusion and pit sealing are the job's bad_field error
        shell_only = opts.get("visible_fusion") is True or bool(opts.get("pit_sealing"))
        return Expected(job={"key": key(rid), "id": rid, "image": msg["image"], "output": msg["output"],
                             "shell_only": shell_only,
                             "files": written_files(msg["output"], opts.get("format"), opts.get("texture")),
                             "intermediates": opts.get("save_intermediates")}, answers=(0, 0))  # (0 to 1 if its id may be taken)
    if kind == "cancel":
        if "id" not in msg:
            return Expected(("error", {"missing_field"}, None))
        return Expected(cancel=key(rid), answers=(0, 1))  # unknown_job, or nothing now: the job's own `cancelled`
    if kind == "shutdown":
        return Expected(answer=("bye", None, rid))  # (never generated with an acceptable id)
    return Expected(("error", {"unknown_type"}, rid))


# ---- the tree, before and after -----------------------------------------------------------------------------
def snapshot(root: Path) -> dict[str, tuple]:
    """Every entry under ``root``: path → (kind, details); a file by inode, size and modification time (a
    rename over it brings another inode, a write in place another time)."""
    import stat

    seen = {}
    for folder, dirs, files in os.walk(root):
        for name in dirs + files:
            p = os.path.join(folder, name)
            st_ = os.lstat(p)
            if stat.S_ISLNK(st_.st_mode):
                seen[p] = ("link", os.readlink(p))
            elif stat.S_ISDIR(st_.st_mode):
                seen[p] = ("dir",)
            elif stat.S_ISREG(st_.st_mode):
                seen[p] = ("file", st_.st_ino, st_.st_size, st_.st_mtime_ns)
            else:
                seen[p] = ("other", stat.S_IFMT(st_.st_mode))
    return seen


def inside(path: str, root: Path) -> bool:
    return path == str(root) or path.startswith(str(root) + os.sep)


# ---- one server for the whole run ----------------------------------------------------------------------------
class FuzzServer(ServerProcess):
    """``ServerProcess`` whose stderr is read as it comes (a long run must not fill the pipe) and kept in a short tail."""

    def __init__(self, *args, cwd):
        super().__init__(*args, cwd=cwd)
        self.stderr_tail: collections.deque[str] = collections.deque(maxlen=40)
        self.stderr_problems: list[str] = []  # tracebacks, failed log records
        threading.Thread(target=self._drain, daemon=True).start()

    def _drain(self):
        for text in self.proc.stderr:
            self.stderr_tail.append(text[:500])
            if "Traceback" in text or "Logging error" in text:
                self.stderr_problems.append(text[:500])


@dataclass(repr=False)
class Fuzz:
    weights: Path
    tree: Tree
    server: FuzzServer | None = None
    ready: dict = field(default_factory=dict)
    n: int = 0
    starts: int = 0
    checked_raw: int = 0
    seconds: float = 0.0
    messages: int = 0
    jobs: collections.Counter = field(default_factory=collections.Counter)
    originals: dict = field(default_factory=dict)
    clean: bool = True  # the last example ran to its end

    def __repr__(self) -> str:
        return f"Fuzz({self.tree.root})"

    def prepare(self) -> None:
        """The tree's fixtures, put back if an earlier example replaced them (an output may name the photo when
        another image is reconstructed, or a link); a server that died in an earlier example is started anew."""
        w = self.tree.work
        if not self.originals:
            self.originals = {p: p.read_bytes() for p in self.tree.inputs.iterdir()}
        for p, data in self.originals.items():
            if os.path.islink(p) or not p.is_file() or p.read_bytes() != data:
                shutil.rmtree(p) if p.is_dir() and not p.is_symlink() else (p.unlink() if os.path.lexists(p) else None)
                p.write_bytes(data)
        for d in (w / "sub" / "deeper", self.tree.root / "out"):
            d.mkdir(parents=True, exist_ok=True)
        if not (w / "fifo").exists():
            os.mkfifo(w / "fifo")
        for name, target in (("link.obj", "../inputs/victim.txt"), ("dangling.obj", "../nowhere/x.obj")):
            if not os.path.islink(w / name):
                if os.path.lexists(w / name):
                    os.unlink(w / name)
                os.symlink(target, w / name)
        if not (w / "existing.obj").is_file():
            (w / "existing.obj").write_text("v 0 0 0\n")
        if self.server is None or self.server.proc.poll() is not None:
            if self.server is not None:
                self.server.close()
            self.server = FuzzServer("--weights", str(self.weights), cwd=self.tree.work)  # (INFO: its log lines quote odd values too)
            self.ready = self.server.next(timeout=300)
            assert self.ready["type"] == "ready", self.ready
            self.starts += 1
            self.checked_raw = 1
        elif not self.clean:  # an earlier example failed half-way (while Hypothesis shrinks): its jobs' events are not ours
            self.barrier()
        self.clean = False

    def _context(self) -> str:
        return "; server stderr: " + "".join(self.server.stderr_tail)[-3000:]

    def check_lines(self) -> None:
        """Every stdout line so far is one ASCII JSON object, newline-terminated, with a documented event."""
        raw = self.server.raw
        for text in raw[self.checked_raw:]:
            assert text.endswith("\n") and text.isascii(), text[:300]
            ev = json.loads(text)
            assert isinstance(ev, dict) and ev.get("type") in EVENT_TYPES and "id" in ev, text[:300]
        self.checked_raw = len(raw)

    def ping(self) -> list[dict]:
        """Ping; the events up to its pong (which must come)."""
        self.n += 1
        rid = f"fz-{self.n}"
        self.server.send({"type": "ping", "id": rid})
        try:
            return self.server.until(lambda e: e["type"] == "pong" and e["id"] == rid, timeout=120)
        except BaseException as exc:
            raise AssertionError(f"no pong after the line ({exc!r}){self._context()}") from None

    def barrier(self) -> list[dict]:
        """A job that fails at once; jobs run in arrival order, so when it has ended every earlier job has too."""
        self.n += 1
        rid = f"fz-barrier-{self.n}"
        self.server.send({"type": "reconstruct", "id": rid, "image": str(self.tree.inputs / "absent.png"),
                          "output": str(self.tree.work / "fz-barrier.obj")})
        try:
            events = self.server.until(lambda e: e["id"] == rid and e["type"] in ("result", "error", "cancelled"), timeout=300)
        except BaseException as exc:
            raise AssertionError(f"the jobs did not end ({exc!r}){self._context()}") from None
        assert events[-1]["type"] == "error" and events[-1]["code"] in ("bad_image", "output_unwritable"), events[-1]
        return events[:-1]


def check_event(ev: dict, ready: dict) -> None:
    if ev["type"] == "error":
        assert ev["code"] in ERROR_CODES, ev
        assert ev["code"] != "internal", f"an input reached an unexpected exception: {ev}"
        msg = ev["message"]
        assert isinstance(msg, str) and msg and "\n" not in msg and "\r" not in msg and len(msg) <= MAX_MESSAGE, ev
    elif ev["type"] == "progress":
        assert ev["stage"] in STAGES and 0.0 <= ev["fraction"] <= 1.0, ev
    elif ev["type"] == "result":
        assert ev["format"] in ("obj", "ply", "glb") and ev["mask_source"] in ("file", "alpha", "salient", "grabcut", "silhouette"), ev
        assert ev["faces"] > 0 and ev["vertices"] > 0 and 0 < ev["threshold"] < 1, ev
    elif ev["type"] == "version":
        assert {k: ev[k] for k in ready if k != "type"} == {k: v for k, v in ready.items() if k != "type"}, ev


def resolve(work: Path, path: str) -> str:
    return os.path.normpath(os.path.join(work, path))  # (no links on the way: the tree's links are file names)


def test_the_fuzzer_draws_every_option_the_server_accepts():
    from genre_backend.frontends.server import _OPTION_KEYS

    assert set(OPTION_KEYS) == set(_OPTION_KEYS) and set(OPTION_KEYS) <= set(PARTS)
    assert {"threshold", "hole_closing", "silhouette_carve", "visible_fusion", "pit_sealing", "primitive_snap", "test_time_mirror",
            "format", "up", "texture", "all_parts"} <= set(RECORD)  # (the options that were written out by hand before the record)


@pytest.fixture(scope="module")
def fuzz(trained, tmp_path_factory):
    import numpy as np
    from PIL import Image

    tree = Tree(tmp_path_factory.mktemp("fuzz"))
    tree.inputs.mkdir()
    tree.work.mkdir()
    views = trained[1]
    shutil.copyfile(views / "box" / "view_000.png", tree.inputs / "photo.png")
    alpha = np.load(views / "box" / "view_000.npz")["mask"] > 0.5
    Image.fromarray(alpha.astype(np.uint8) * 255, "L").save(tree.inputs / "mask.png")
    (tree.inputs / "victim.txt").write_text("a file a link points at: never written through the link")
    f = Fuzz(trained[0], tree)
    yield f
    # the run's own record, then a shutdown the server accepts: an odd but valid id is echoed by `bye`
    print(f"\nfuzz: {f.messages} lines in {f.seconds:.1f} s, jobs {dict(f.jobs)}, server started {f.starts}×")
    if f.server is not None and f.server.proc.poll() is None:
        odd = int("7" * 4_000)
        f.server.send_bytes(to_line({"type": "shutdown", "id": Raw(str(odd)), "extra": ["\udce9", 1e300]}, False))
        bye = f.server.until(lambda e: e["type"] == "bye")[-1]
        assert bye["id"] == odd
        assert f.server.close() == 0
        f.check_lines()
    leftovers = [p for p in snapshot(tree.root) if is_temporary_name(os.path.basename(p))]
    assert not leftovers, leftovers
    assert f.starts == 1, f"the server had to be started {f.starts} times: an example stopped it (see the failure above)"


_PHOTO = b'"image": "@ROOT@/inputs/photo.png"'
REGRESSIONS = [  # lines that broke the server before issue 18's fixes (run first, on every run)
    [b'{"type": "reconstruct", "id": 1, ' + _PHOTO + b', "output": "r.obj", "options": {"threshold": 1' + b"0" * 400 + b"}}"],  # crashed the reader
    [b'{"type": "reconstruct", "id": 2, ' + _PHOTO + b', "output": "r.obj", "options": ""}'],  # a falsy non-object was taken for {}
    [b'{"type": "reconstruct", "id": 3, "image": "' + b"x" * 300 + b'", "output": "r.obj"}'],  # a name too long: internal
    [b'{"type": "reconstruct", "id": 4, ' + _PHOTO + b', "mask": "../' + b"m" * 300 + b'", "output": "r.obj"}'],
    [b'{"type": "reconstruct", "id": 5, ' + _PHOTO + b', "output": "r.obj", "options": {"save_intermediates": "' + b"i" * 300 + b'"}}'],
    [b'{"type": "reconstruct", "id": 6, "image": "a\\u0000b", "output": "r.obj"}',  # NUL and lone surrogates: one answer for all paths
     b'{"type": "reconstruct", "id": 7, ' + _PHOTO + b', "output": "r\\ud800.obj"}',
     b'{"type": "reconstruct", "id": 8, ' + _PHOTO + b', "output": "r.obj", "mask": "\\udfff"}'],
    [b'{"type": ' + b"[" * 980 + b"]" * 980 + b"}", b'{"type": "ping", "id": ' + b"[" * 980 + b"]" * 980 + b"}"],  # deep values quoted back
]


def _with_regressions(test):
    for lines in reversed(REGRESSIONS):
        test = example(lines=lines)(test)
    return test


@pytest.mark.slow
@settings(max_examples=EXAMPLES, deadline=None, derandomize=True, database=None, print_blob=False,
          suppress_health_check=[HealthCheck.too_slow, HealthCheck.data_too_large, HealthCheck.large_base_example])
@given(lines=EXAMPLE)
@_with_regressions
def test_fuzzed_lines_never_break_the_server_or_write_elsewhere(fuzz, lines):
    work, root = fuzz.tree.work, fuzz.tree.root
    lines = [line.replace(ROOT.encode(), os.fsencode(root)) for line in lines]
    plans = [expect(as_the_server_reads(line)) for line in lines]
    assume(not any(p.answer and p.answer[0] == "bye" for p in plans))  # (an odd field that made a shutdown acceptable)
    for plan in plans:  # the job may write: every path it can write lies in the tree (also guards the machine)
        if plan.job and isinstance(plan.job["image"], str) and os.path.isfile(resolve(work, plan.job["image"])):
            for p in (*plan.job["files"], plan.job["intermediates"]):
                assume(p is None or resolve(work, p) in ("/dev/null", "/") or inside(resolve(work, p), root))
    fuzz.prepare()
    before = snapshot(root)
    t0 = time.perf_counter()
    events: list[dict] = []
    for i, (line, plan) in enumerate(zip(lines, plans)):
        note(f"line {i}: {line[:400]!r}{'…' if len(line) > 400 else ''} → {plan}")
        fuzz.server.send_bytes(line)
        window = fuzz.ping()[:-1]
        fuzz.check_lines()
        for ev in window:
            check_event(ev, fuzz.ready)
        if plan.answer is not None:
            kind, codes, rid = plan.answer
            assert any(ev["type"] == kind and key(ev["id"]) == key(rid) and (codes is None or ev.get("code") in codes) for ev in window), \
                f"expected {plan.answer} after line {i}, got {window}"
        if plan.cancel is not None and not any(p.job and p.job["key"] == plan.cancel for p in plans[:i]):
            assert any(ev["type"] == "error" and ev["code"] == "unknown_job" and key(ev["id"]) == plan.cancel for ev in window), window
        lo, hi = plan.answers
        if plan.job and any(p.job and p.job["key"] == plan.job["key"] for p in plans[:i]):
            hi = 1  # a job of that id may still be queued: refused as a duplicate
        direct = [ev for ev in window if ev["type"] in ("pong", "version") or (ev["type"] == "error" and ev["code"] in DIRECT_CODES)]
        assert lo <= len(direct) <= hi, f"line {i} got {len(direct)} direct answers, expected {lo} to {hi}: {direct}"
        events += window
    events += fuzz.barrier()
    fuzz.check_lines()
    assert not fuzz.server.stderr_problems, fuzz._context()
    for ev in events:
        check_event(ev, fuzz.ready)
    fuzz.seconds += time.perf_counter() - t0
    fuzz.messages += len(lines)

    # every accepted job ends once; a result names its output; progress runs forward
    jobs = [p.job for p in plans if p.job]
    keys = collections.Counter(j["key"] for j in jobs)
    other_keys = {key(p.answer[2]) for p in plans if p.answer and p.answer[0] == "error"}
    for job in jobs:
        mine = [ev for ev in events if key(ev["id"]) == job["key"]]
        ends = [ev for ev in mine if ev["type"] in ("result", "cancelled") or job_failure(ev, job)]
        if keys[job["key"]] == 1:
            assert len(ends) == 1, (job, mine)
            assert not [ev for ev in mine if ev["type"] == "error" and not job_failure(ev, job) and ev["code"] != "unknown_job"] \
                or job["key"] in other_keys or any(p.unsure for p in plans), (job, mine)  # (refused: another line with its id)
            fuzz.jobs[ends[0]["type"] if ends[0]["type"] != "error" else ends[0]["code"]] += 1
        # progress runs forward within each run of that id (a second job of the id may run once the first ended)
        fractions: list[float] = []
        for ev in mine:
            if ev["type"] == "progress":
                assert not fractions or ev["fraction"] >= fractions[-1], mine
                fractions.append(ev["fraction"])
            elif ev["type"] in ("result", "cancelled", "error"):  # (an end, or a refusal of a line with the id)
                fractions = []
        for ev in ends:
            if ev["type"] == "result":
                assert any(j["key"] == job["key"] and ev["mesh"] == str(PurePosixPath(j["output"])) for j in jobs), (ev, jobs)
                assert os.path.isfile(resolve(work, ev["mesh"])), ev

    # the tree: new, changed or removed entries only where an accepted request asked for output
    after = snapshot(root)
    files, folders = set(), set()
    for job in jobs:
        files.update(resolve(work, f) for f in job["files"])
        if job["intermediates"] is not None:
            folder = resolve(work, job["intermediates"])
            folders.add(folder)
            while inside(folder, root) and folder != str(root):  # (created with its parents)
                folder = os.path.dirname(folder)
                folders.add(folder)
    cancelled_outputs = {resolve(work, j["output"]) for j in jobs if keys[j["key"]] == 1 and any(
        key(ev["id"]) == j["key"] and ev["type"] == "cancelled" for ev in events)}
    for path in sorted(set(before) | set(after)):
        if before.get(path) == after.get(path):
            continue
        assert path in after, f"{path!r} was removed"
        kind = after[path][0]
        allowed = (kind == "file" and (path in files or (path.endswith(".png") and os.path.dirname(path) in folders))) or \
                  (kind == "dir" and path in folders)
        assert allowed, f"{path!r} was {'changed' if path in before else 'created'} ({after[path]}), no accepted request named it"
        assert path not in cancelled_outputs or sum(resolve(work, j["output"]) == path for j in jobs) > 1, f"cancelled job wrote {path!r}"
    fuzz.clean = True
