"""Named weights: what each known checkpoint is, where it lives, and what it fits (data, no I/O).

    entry = lookup("re10k-256x256-small")
    entry.source        # Source(kind="hf", repo="binghe-sjtu/SurfSplat", filename="re10k-256x256-surfsplat-small.pth")
    entry.preset, entry.resolution, entry.adapter, entry.licence

Three kinds of source:
- "hf": a file of a Hugging Face repository, fetched and cached by `huggingface_hub` (it honours
  HF_HUB_OFFLINE, HF_HOME and HF_HUB_CACHE, resumes and verifies downloads);
- "url": a file on a public web server, cached by `torch.hub` under TORCH_HOME
  (`<hub dir>/checkpoints/<file>`); when the file name carries a SHA-256 prefix
  (`name-<hex>.pth`, the torch hub convention) the download is checked against it;
- "package": a file shipped inside this package (`surfsplat/model/weights/`), nothing to fetch.

`surfsplat.model.pretrained` turns an entry into a local file and a model. Names never contain a
slash or a file suffix, so `./name` always means a path. A user can point at a file the registry
does not know (or a release file the hub holds under another path) with `hf://owner/repo/path/file`.
"""

from __future__ import annotations

import re
from dataclasses import dataclass, replace
from pathlib import PurePosixPath
from typing import Literal

from ..utils.checks import SurfSplatInputError

SourceKind = Literal["hf", "url", "package"]
# How a file's tensors are named: the release's encoder, our own .safetensors + .json pair, the two
# training initialisations, and the two LPIPS files.
Layout = Literal["release", "surfsplat", "depth-anything-v2", "unimatch", "torchvision-vgg16", "lpips-lin"]
Role = Literal["model", "monodepth", "mvdepth", "lpips"]

RELEASE_REPO = "binghe-sjtu/SurfSplat"
HF_SCHEME = "hf://"
PACKAGE_WEIGHTS = "model/weights"  # folder inside the surfsplat package for shipped weights

# The release's own licence (its repository's LICENSE file).
RELEASE_LICENCE = "CC BY-NC-SA 4.0 (SurfSplat release: non-commercial, share-alike)"


@dataclass(frozen=True)
class Source:
    """Where a file lives."""

    kind: SourceKind
    filename: str  # hf: path inside the repository; url: cached file name; package: file in PACKAGE_WEIGHTS
    repo: str | None = None  # hf: owner/name
    revision: str | None = None  # hf: branch, tag or commit (None: the hub's default, main)
    url: str | None = None  # url: where to download it

    def describe(self) -> str:
        if self.kind == "hf":
            at = f"@{self.revision}" if self.revision else ""
            return f"{HF_SCHEME}{self.repo}{at}/{self.filename}"
        if self.kind == "url":
            return str(self.url)
        return f"surfsplat/{PACKAGE_WEIGHTS}/{self.filename} (shipped with the package)"


@dataclass(frozen=True)
class WeightsEntry:
    """One named checkpoint and what it fits."""

    name: str
    role: Role  # model: a whole network; monodepth / mvdepth: a training initialisation; lpips
    layout: Layout
    source: Source
    description: str  # one line for `surfsplat weights list`
    licence: str  # licence of the weights (not of this code)
    preset: str | None = None  # encoder preset it fits (surfsplat.model.surfsplat.PRESETS)
    resolution: tuple[int, int] | None = None  # (H, W) it was trained at
    adapter: Literal["paper", "official"] | None = None  # adapter mode it was trained with


def _release(name: str, preset: str, resolution: tuple[int, int]) -> WeightsEntry:
    h, w = resolution
    return WeightsEntry(
        name=name,
        role="model",
        layout="release",
        source=Source("hf", f"re10k-{h}x{w}-surfsplat-{preset}.pth", repo=RELEASE_REPO),
        description=f"released SurfSplat-{preset}, RealEstate10K, 2 views, {h}x{w}",
        licence=RELEASE_LICENCE,
        preset=preset,
        resolution=resolution,
        # it was trained with the release's adapter, whose quirks its weights compensate
        adapter="official",
    )


def _depth_anything(size: str, preset: str, licence: str) -> WeightsEntry:
    vit = {"Small": "vits", "Base": "vitb", "Large": "vitl"}[size]
    return WeightsEntry(
        name=f"depth-anything-v2-{vit}",
        role="monodepth",
        layout="depth-anything-v2",
        source=Source("hf", f"depth_anything_v2_{vit}.pth", repo=f"depth-anything/Depth-Anything-V2-{size}"),
        description=f"Depth Anything V2 ViT-{size[0]} (monocular branch init of the {preset} preset)",
        licence=licence,
        preset=preset,
    )


_ENTRIES: tuple[WeightsEntry, ...] = (
    # The release's checkpoints, named as its scripts/datasets_test.sh names them.
    _release("re10k-256x256-small", "small", (256, 256)),
    _release("re10k-256x256-base", "base", (256, 256)),
    _release("re10k-256x256-large", "large", (256, 256)),
    _release("re10k-256x448-base", "base", (256, 448)),
    # The paper's training initialisation (the release's checkpointing.pretrained_monodepth / _mvdepth).
    _depth_anything("Small", "small", "Apache-2.0"),
    _depth_anything("Base", "base", "CC BY-NC 4.0 (non-commercial)"),
    _depth_anything("Large", "large", "CC BY-NC 4.0 (non-commercial)"),
    WeightsEntry(
        name="unimatch-gmflow-scale1",
        role="mvdepth",
        layout="unimatch",
        source=Source(
            "url",
            "gmflow-scale1-things-e9887eda.pth",
            url="https://s3.eu-central-1.amazonaws.com/avg-projects/unimatch/pretrained/gmflow-scale1-things-e9887eda.pth",
        ),
        description="UniMatch GMFlow (1 scale, FlyingThings): CNN + multi-view transformer init (small/base/large)",
        licence="MIT (UniMatch)",
    ),
    # LPIPS-VGG v0.1: torchvision's ImageNet trunk and the lpips package's linear heads.
    WeightsEntry(
        name="lpips-vgg16",
        role="lpips",
        layout="torchvision-vgg16",
        source=Source("url", "vgg16-397923af.pth", url="https://download.pytorch.org/models/vgg16-397923af.pth"),
        description="torchvision's ImageNet VGG16, the LPIPS trunk",
        licence="CC BY 4.0 (VGG16 weights, Simonyan & Zisserman), as distributed by torchvision",
    ),
    WeightsEntry(
        name="lpips-vgg-lin",
        role="lpips",
        layout="lpips-lin",
        source=Source(
            "url",
            "lpips-v0.1-vgg.pth",  # cached under this name: the upstream name, vgg.pth, says too little
            url="https://github.com/richzhang/PerceptualSimilarity/raw/master/lpips/weights/v0.1/vgg.pth",
        ),
        description="LPIPS v0.1 linear heads for the VGG trunk (the lpips package's weights/v0.1/vgg.pth)",
        licence="BSD-2-Clause (lpips)",
    ),
    # Our own model, shipped inside the package (trained on the procedural synthetic rooms).
    WeightsEntry(
        name="tiny-synthetic",
        role="model",
        layout="surfsplat",
        source=Source("package", "tiny-synthetic.safetensors"),
        description="our tiny model trained on procedural synthetic rooms (CPU demo quality)",
        licence="MIT (this package)",
        preset="tiny",
        resolution=(64, 64),
        adapter="paper",
    ),
)

REGISTRY: dict[str, WeightsEntry] = {entry.name: entry for entry in _ENTRIES}

_NAME = re.compile(r"^[a-z0-9][a-z0-9-]*$")


def known_names(role: Role | None = None) -> list[str]:
    return [name for name, entry in REGISTRY.items() if role is None or entry.role == role]


def looks_like_name(text: str) -> bool:
    """True for strings shaped like registry names: lower case, digits and dashes (no slash, no suffix)."""
    return bool(_NAME.match(text))


def lookup(name: str, role: Role | None = None) -> WeightsEntry:
    """The entry called `name` (or described by an `hf://` address); one error listing the known names."""
    if name.startswith(HF_SCHEME):
        return entry_for_hf_uri(name)
    entry = REGISTRY.get(name)
    what = "pretrained weights" if role is None else f"{role} weights"
    known = ", ".join(known_names(role))
    if entry is None:
        raise SurfSplatInputError(f"unknown {what} name {name!r} (known: {known}; or give a file path)")
    if role is not None and entry.role != role:
        raise SurfSplatInputError(f"{name} holds {entry.role} weights ({entry.description}), not {what} ({known})")
    return entry


def parse_hf_uri(uri: str) -> Source:
    """`hf://owner/repo[@revision]/path/in/repo/file` -> an "hf" Source."""
    rest = uri[len(HF_SCHEME) :] if uri.startswith(HF_SCHEME) else ""
    parts = rest.split("/")
    if len(parts) < 3 or not all(parts):
        raise SurfSplatInputError(f"{uri}: expected {HF_SCHEME}owner/repo[@revision]/path/to/file")
    owner, repo, *path = parts
    repo, _, revision = repo.partition("@")
    return Source("hf", "/".join(path), repo=f"{owner}/{repo}", revision=revision or None)


def entry_for_hf_uri(uri: str) -> WeightsEntry:
    """An entry for a user-given `hf://` file: a registry entry's metadata when it names the same file
    (same repository or a copy with the same file name), else a release-layout model of unknown preset."""
    source = parse_hf_uri(uri)
    basename = PurePosixPath(source.filename).name
    for entry in REGISTRY.values():
        if entry.source.kind == "hf" and PurePosixPath(entry.source.filename).name == basename:
            return replace(entry, name=uri, source=source)
    layout: Layout = "surfsplat" if basename.endswith((".safetensors", ".json")) else "release"
    return WeightsEntry(
        name=uri,
        role="model",
        layout=layout,
        source=source,
        description=f"user-given file {uri}",
        licence="unknown (see the repository)",
        adapter="official" if layout == "release" else None,
    )
