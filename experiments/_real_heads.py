"""The real-anatomy heads the study experiments run on, and their shared command-line options.

The MNI152-based head (`mni152_anatomy`, from installed nilearn/MNE data) and the ANTs 19.5-year
head (`ants_anatomy`, from ../shared/data/heads/), layered, surfaced and meshed with the library's
defaults, with electrodes spread over the upper head.
"""

import argparse
from pathlib import Path

from jaxhead.electrodes import place_electrodes
from jaxhead.fem import build_forward_model
from jaxhead.geometry import extract_surfaces, make_layers, tetrahedralize
from jaxhead.segmentation import ants_anatomy, mni152_anatomy

HEADS = {"mni152": lambda folder: mni152_anatomy(), "ants": ants_anatomy}


def add_head_arguments(ap: argparse.ArgumentParser) -> None:
    """--voxel-mm, --heads, --n-elec and --ants-dir."""
    ap.add_argument("--voxel-mm", type=float, default=4.0)
    ap.add_argument("--heads", nargs="+", default=list(HEADS), choices=list(HEADS))
    ap.add_argument("--n-elec", type=int, default=32)
    ap.add_argument("--ants-dir", default=str(Path(__file__).parents[1] / ".." / "shared" / "data"
                                              / "heads"), help="folder of c1..c6ANTS19-5Years_head.jnii")


def head_model(name: str, args: argparse.Namespace):
    """(mesh, electrodes, forward model) of head `name` at `args.voxel_mm` with `args.n_elec` electrodes."""
    labels = HEADS[name](args.ants_dir).resampled(args.voxel_mm).labels()
    mesh = tetrahedralize(extract_surfaces(make_layers(labels)))
    el = place_electrodes(mesh, args.n_elec, radius_mm=5.0)
    return mesh, el, build_forward_model(mesh, el)
