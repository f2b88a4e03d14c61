"""results/ stays lean: at most 40 files and 3 MB, and every results/... path the docs cite exists.

What was removed from results/ is in git history (results/README.md says which commit)."""

import glob
import re
import subprocess
from pathlib import Path

ROOT = Path(__file__).resolve().parents[2]
RESULTS = ROOT / "results"
MAX_FILES = 40
MAX_BYTES = 3_000_000
CITING = ["README.md", "ARCHITECTURE.md", "genre_backend/weights/MODEL_CARD.md", "examples/README.md",
          *sorted(str(p.relative_to(ROOT)) for p in (ROOT / "docs").rglob("*.md"))]
# a repository path: not part of another path ($GENRE_HOME/results/…, …/results/…) or a word
CITED = re.compile(r"(?<![\w/$.~-])results/[\w.*/-]*")


def _files():
    """The files under results/ that git tracks or would track (ignored outputs of a local run do not count)."""
    try:
        out = subprocess.run(["git", "ls-files", "--cached", "--others", "--exclude-standard", "results"],
                             cwd=ROOT, capture_output=True, text=True, check=True).stdout
        return [ROOT / line for line in out.splitlines() if (ROOT / line).is_file()]
    except (OSError, subprocess.CalledProcessError):  # not a git checkout
        return [p for p in RESULTS.rglob("*") if p.is_file()]


def test_results_within_budget():
    files = _files()
    size = sum(p.stat().st_size for p in files)
    assert len(files) <= MAX_FILES, f"results/ has {len(files)} files, the budget is {MAX_FILES}"
    assert size <= MAX_BYTES, f"results/ takes {size / 1e6:.2f} MB, the budget is {MAX_BYTES / 1e6:.0f} MB"


def cited_paths():
    for name in CITING:
        path = ROOT / name
        if not path.is_file():
            continue
        for lineno, line in enumerate(path.read_text(encoding="utf-8").splitlines(), 1):
            for m in CITED.finditer(line):
                cited = m.group(0).rstrip(".")
                if "<" in cited or cited in {"results/", "results"}:
                    continue
                yield name, lineno, cited


def test_cited_results_exist():
    assert any(True for _ in cited_paths()), "the pattern finds no citation: check CITED"
    missing = [f"{name}:{lineno}: {cited}" for name, lineno, cited in cited_paths()
               if not glob.glob(str(ROOT / cited))]
    assert not missing, "cited but not in results/:\n" + "\n".join(missing)
