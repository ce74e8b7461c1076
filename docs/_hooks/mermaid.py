"""Mermaid's script, served by the site itself: the diagrams render offline.

The docs draw their diagrams as ``mermaid`` code blocks (pymdownx.superfences' custom fence,
mkdocs.yml); Material renders them with Mermaid in the browser, and loads Mermaid from a CDN
unless the page already defines it. This hook makes the page define it: it adds Mermaid's
one-file build, ``dist/mermaid.min.js`` of the npm package ``mermaid`` at the version pinned
below, to the site (``assets/javascripts/mermaid.min.js``, listed in ``extra_javascript``).

The file is fetched once with npm's own client (``npm pack``, which checks the package's
integrity against the registry), checked against the SHA-256 pinned below and kept in the
user's cache (``$XDG_CACHE_HOME/evclock``, default ``~/.cache/evclock``); later builds read it
from there. Without npm or the registry the build fails and says how to provide the file.
"""

from __future__ import annotations

import hashlib
import os
import shutil
import subprocess
import tarfile
import tempfile
from pathlib import Path
from typing import Any

from mkdocs.exceptions import PluginError
from mkdocs.structure.files import File, Files

#: Mermaid's version (Material 9's integration is written for Mermaid 11) and the SHA-256 of
#: its ``dist/mermaid.min.js``.
VERSION = "11.17.2"
SHA256 = "581ed7d74bd9048d0e3a91363927d72ef22942d7722546b27f7cc29e35390eb8"
#: Where the site serves it.
SITE_PATH = "assets/javascripts/mermaid.min.js"


def cached_script() -> Path:
    """Where the checked script is kept between builds."""
    cache = Path(os.environ.get("XDG_CACHE_HOME") or Path.home() / ".cache") / "evclock"
    return cache / f"mermaid-{VERSION}.min.js"


def _digest(data: bytes) -> str:
    return hashlib.sha256(data).hexdigest()


def _fetch(target: Path) -> None:
    """``npm pack mermaid@VERSION``, then its ``dist/mermaid.min.js``, checked, to ``target``."""
    npm = shutil.which("npm")
    advice = (
        f"put dist/mermaid.min.js of the npm package mermaid@{VERSION} (SHA-256 {SHA256}) at "
        f"{target}"
    )
    if npm is None:
        raise PluginError(
            f"the docs' diagrams need Mermaid's script, which the site serves itself; npm is "
            f"not installed to fetch it: install npm (Debian: apt-get install npm), or {advice}"
        )
    with tempfile.TemporaryDirectory() as folder:
        result = subprocess.run(
            [npm, "pack", f"mermaid@{VERSION}", "--silent", "--pack-destination", folder],
            capture_output=True,
            text=True,
            timeout=600,
            check=False,
        )
        if result.returncode != 0:
            raise PluginError(
                f"npm pack mermaid@{VERSION} failed (exit {result.returncode}): "
                f"{result.stderr.strip()[-500:]}; {advice}"
            )
        with tarfile.open(Path(folder) / f"mermaid-{VERSION}.tgz") as archive:
            member = archive.extractfile("package/dist/mermaid.min.js")
            assert member is not None  # a regular file in every release
            data = member.read()
    if _digest(data) != SHA256:
        raise PluginError(
            f"mermaid@{VERSION}'s dist/mermaid.min.js from npm does not have the pinned "
            f"SHA-256 {SHA256}; refusing to serve it"
        )
    target.parent.mkdir(parents=True, exist_ok=True)
    partial = target.with_suffix(f".{os.getpid()}.part")
    partial.write_bytes(data)
    partial.replace(target)  # atomic: concurrent builds see the whole file or none


def script() -> Path:
    """Mermaid's script, checked: from the cache, fetched first if needed."""
    path = cached_script()
    if not path.is_file() or _digest(path.read_bytes()) != SHA256:
        _fetch(path)
    return path


def on_config(config: Any) -> Any:
    config.extra_javascript.append(SITE_PATH)
    return config


def on_files(files: Files, config: Any) -> Files:
    files.append(File.generated(config, SITE_PATH, abs_src_path=str(script())))
    return files
