"""`pip install ./clients/python`, as a user installs it, leaves nothing in the work tree that
`.gitignore` does not cover (issue 47: setuptools' `build/` and `scancorr.egg-info/` were left
beside the sources, untracked and not ignored); and the deployment files the package's docs
name are there."""

from __future__ import annotations

import fnmatch
import pathlib
import shutil
import subprocess
import sys

from conftest import ROOT


def ignored(rel: str) -> bool:
    """Whether the repository's `.gitignore` ignores `rel` (a folder, relative to the root), by
    its rules as git reads them: `/a/b` from the root, `a` or `*.x` at any depth, a trailing
    `/` for folders, `!` to take back; the last rule that matches decides, and a folder's
    rule covers what is in it."""
    rules = [l.strip() for l in (ROOT / ".gitignore").read_text().splitlines()]
    rules = [l for l in rules if l and not l.startswith("#")]
    parts = rel.strip("/").split("/")
    for depth in range(1, len(parts) + 1):
        path = "/".join(parts[:depth])
        verdict = False
        for r in rules:
            neg = r.startswith("!")
            p = r[1:] if neg else r
            p = p.rstrip("/")  # every path here is a folder
            if p.startswith("/") or "/" in p:
                hit = fnmatch.fnmatchcase(path, p.lstrip("/"))
            else:
                hit = fnmatch.fnmatchcase(parts[depth - 1], p)
            if hit:
                verdict = not neg
        if verdict:
            return True
    return False


def test_pip_install_leaves_only_ignored_files(tmp_path: pathlib.Path) -> None:
    pkg = ROOT / "clients" / "python"
    r = subprocess.run(
        [sys.executable, "-m", "pip", "install", "--quiet", "--no-deps", "--no-build-isolation",
         "--target", str(tmp_path / "site"), str(pkg)],
        capture_output=True, text=True, timeout=180,
    )
    assert r.returncode == 0, r.stderr
    made = sorted(p for p in pkg.iterdir() if p.name in ("build", "dist") or p.name.endswith(".egg-info"))
    assert made, "pip install left no build folder: nothing to check (has setuptools changed where it builds?)"
    for p in made:
        rel = p.relative_to(ROOT).as_posix()
        assert ignored(rel), f"{rel}/ (made by pip install ./clients/python) is not in .gitignore"
        if shutil.which("git") and (ROOT / ".git").exists():
            g = subprocess.run(["git", "-C", str(ROOT), "check-ignore", "-q", rel + "/"], timeout=30)
            assert g.returncode == 0, f"git does not ignore {rel}/"
    # The matcher is no yes-man: the sources are not ignored.
    assert not ignored("clients/python/scancorr") and not ignored("clients/python/tests")


def test_the_package_names_only_deployment_files_that_exist() -> None:
    """Every `deploy/…` file the package's README, examples and messages name is in the
    repository (issue 47: the docs named a `deploy/app.json5` there is not)."""
    import re

    pkg = ROOT / "clients" / "python"
    files = [pkg / "README.md", *sorted((pkg / "scancorr").glob("*.py")), *sorted((pkg / "examples").glob("*.py"))]
    named = {
        (f.relative_to(ROOT).as_posix(), m.rstrip(".,;:)`"))
        for f in files
        for m in re.findall(r"deploy/[A-Za-z0-9_./-]+", f.read_text())
    }
    named = {(f, m) for f, m in named if m.rstrip("/") != "deploy"}
    assert len(named) >= 3, named
    missing = sorted(f"{f}: {m}" for f, m in named if not (ROOT / m).exists())
    assert not missing, "named but not in the repository:\n" + "\n".join(missing)
