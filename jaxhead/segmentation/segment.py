"""`segment` (and `segment_reported`): atlas registration + EM/MRF tissue classification of a head MRI or CT.  [jax]

Pipeline (one method for both modalities, as the seed's CT branch: Vonach et al. 2012):

1. register the atlas template to the scan (affine on a pyramid, then cubic B-spline; register.py),
2. resample the atlas priors onto the scan's grid through that transform,
3. EM with atlas priors, prior relaxation, Potts MRF and (MRI) bias field on a strided sample of the
   grid (`em_sample_mm`, as SPM samples every 3 mm to estimate its mixture), em.py; by default for CT
   on the scan after edge-preserving smoothing tied to its estimated noise (`denoise`, denoise.py),
4. posteriors on the full grid at the fitted parameters with mean-field MRF sweeps,
4a. MRI: scalp-labelled voxels that the segmented skull encloses (an adult's marrow, as bright as fat)
   given the skull's prior, and 3-4 again (`SegmentConfig.marrow_inside_skull`),
4b. MRI: the CSF/skull change point in depth between the segmented brain and scalp learnt from the
   scan's own intensities in the dark band between them (CSF inside the skull), the CSF/skull priors
   shared by a step at it, and 3-4 again (`depth_prior.fit_layer_split`, `SegmentConfig.layer_split`;
   optionally first the atlas's profile in depth, `SegmentConfig.depth_prior`),
4c. MRI: the compact tables around a fat-bright marrow that the EM gave to CSF or the scalp (a scanner's blur
   darkens them to CSF's and muscle's level) relabelled skull (`marrow_tables`, `SegmentConfig.marrow_tables`),
5. CT: the bone surface and the skin relabelled by the partial-volume majority rule (`bone_majority`,
   `air_majority`), and scalp the skull encloses beside the brain or CSF relabelled (`scalp_outside_skull`),
6. hard labels = argmax of the five class posteriors (BACKGROUND, BRAIN, CSF, SKULL, SCALP).

MRI is modelled in log intensity (multiplicative bias -> additive; Van Leemput et al. 1999); CT in
Hounsfield units with no bias field.

What the intensity model assumes (and what it learns from the scan):

- Each class is a mixture of a few Gaussians (DEFAULT_GAUSSIANS) whose means, variances and weights
  are all fitted to this scan; nothing about the tissues' contrast is fixed, except on CT the order
  of CSF below brain by CSF_BRAIN_MARGIN_HU and of CSF's bone mixture below bone (physical Hounsfield
  units; `csf_below_brain`, `csf_mix_below_bone`) and on MRI, taken to be T1-weighted, CSF's
  partial-volume Gaussian at or below the brain's lowest (`csf_mix_below_brain`). The start is the
  registered atlas priors' weighted intensity quantiles of the scan itself (em._init_params), so an
  MRI with another contrast ratio, a dark or a fat-bright scalp, or a CT with another scanner's HU
  calibration starts from its own intensities, not the atlas template's.
- The registered atlas is right to within its blur (priors ~3 mm wide plus a 5 % share of every
  head tissue inside the head): a tissue the atlas puts nowhere near (facial bones outside the
  atlas's skull) is found through that share and the prior relaxation.
- MRI: magnitude image, positive, T1-like or not (any ordering of tissue intensities), a smooth
  multiplicative bias field (Legendre polynomial, degree 4; tens of per cent), noise small against
  the tissue contrasts (a few per cent). CT: Hounsfield units (air near -1000), no bias field.
- Tissue boundaries are smooth on the voxel scale (Potts MRF, beta).
- MRI: scalp lies outside the skull, so a scalp-labelled layer the skull encloses is its marrow
  (`marrow_inside_skull`; voxels of at most MARROW_MAX_VOXEL_MM, where the tables can close around it).
  Compact bone is dark in every MR contrast, so scalp-labelled voxels as dark as the skull's tables, deeper
  than the skin's partial volume with air (SKIN_LAYER_MM), enclose it too (an outer table the scalp took).
- MRI: an adult's diploe lies between two compact tables 1-2 mm thick (MARROW_TABLE_MM), so dark voxels the EM
  gave to CSF or the scalp within that reach of exposed fat-bright marrow are those tables (`marrow_tables`).
- MRI: between the brain and the scalp, CSF lies inside the skull, and within a neighbourhood of
  LAYER_SPLIT_MM the CSF's share of the band's depth changes little (`layer_split`).
- `denoise`: the noise is uncorrelated between voxels and roughly stationary (CT: additive, its sd
  estimated from neighbour differences; MRI: Rician magnitude, its channel sd estimated from the air
  around the head, Rayleigh), and tissue steps of more than ~2 noise sd are edges (MRI: in the
  magnitude, before the log, where the noise is the same in every tissue).
- The scan is a head in the orientation its affine states (checked: `check_orientation`,
  `check_registration`).

Precision: the default is float32. Registration similarity and EM posteriors are statistics of
10^5-10^7 voxels whose noise (MRI ~3 %, CT ~15 HU) is 10^4-10^5 times float32's resolution; the EM's
sums are nested per axis so their rounding stays ~1e-5 relative. float32 halves the memory (the
(5, x, y, z) posteriors of a 1 mm head are 140 MB) and roughly doubles the speed. `precision="float64"`
is there for checks (and is what the tests use where they compare with references).
"""

from __future__ import annotations

import itertools
import logging
import time
from collections.abc import Mapping
from concurrent.futures import ThreadPoolExecutor
from dataclasses import dataclass, field, replace
from typing import Literal

import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np
from nibabel.orientations import aff2axcodes as nib_axcodes
from scipy import ndimage

from ..tissue import Tissue
from ..volume import LabelMap, Volume, voxel_sizes
from .atlas import N_CLASSES, Atlas, check_atlas_kind, default_atlas, regional_proportions, with_proportions
from .depth_prior import (csf_depth_profile, fit_layer_split, largest_component, layer_depth, with_depth_profile,
                          with_local_split)
from .denoise import diffuse, log_noise_table, noise_sd, rayleigh_noise_sd
from .em import EMOptions, MixtureParams, NoiseFloor, bias_field, fit_mixture, infer_posteriors
from .register import (
    AffineTransform, BSplineTransform, RegisterConfig, Transform, _level_factors, centre_of_mass, downsample, nmi,
    register, resample,
)
from .templates import UNMODELLED_CLASSES
from .warp_refine import alternate, warp_problem

log = logging.getLogger(__name__)

#: Gaussians per class by default (BACKGROUND, BRAIN, CSF, SKULL, SCALP): one per tissue the class
#: is made of, plus one for a partial-volume tail where a thin layer borders a very different one
#: (without a home of their own, those voxels drag the nearest broad Gaussian off its tissue: CT CSF,
#: 1-5 mm between brain at 30 HU and bone at 1000+ HU, loses its Gaussian to the bone tail, and the
#: air/skin boundary voxels at ~-500 HU pull whichever Gaussian is widest):
#: MRI: air (Rician noise floor, skewed in log) 2; brain grey + white 2; CSF pure + partial volume 2;
#: skull compact tables (dark) + diploe (fatty marrow, bright) + partial volume 3; scalp skin/muscle +
#: fat + partial volume with air 3.
#: CT: air + partial volume 2; brain grey/white (30-40 HU, one blurred peak) 1; CSF pure + partial
#: volume with bone 2; skull cortical + diploe 2; scalp fat (-90 HU) + skin/muscle (+40 HU) + partial
#: volume with air 3.
DEFAULT_GAUSSIANS = {"mri": (2, 2, 2, 3, 3), "ct": (2, 1, 2, 2, 3)}
#: With `partial_volume=True`: the free ("pure") Gaussians, one per tissue (MRI: air 2, brain grey +
#: white 2, CSF 1, skull tables + diploe 2, scalp skin/muscle + fat 2; CT: air 1, brain 1, CSF 1,
#: skull cortical + diploe 2, scalp fat + skin/muscle 2), and every pair of bordering layers in
#: PV_PAIRS adds two tied partial-volume Gaussians (one per class; em.py), so that boundary voxels
#: go to the tissue that fills more than half of them. Measured (experiments/results/
#: segmentation_accuracy.md, "with PV Gaussians"): CT scalp (air/skin boundary) and MRI at 6 % noise
#: better; MRI skull at 3 % and CT CSF worse (the mixing line is drawn to the nearest pure skull
#: Gaussian, the diploe, not the inner table that borders CSF); so it is off by default.
DEFAULT_GAUSSIANS_PV = {"mri": (2, 2, 1, 2, 2), "ct": (1, 1, 1, 2, 2)}
#: Bordering layers of a head, outside in (the classes are nested: air | scalp | skull | CSF | brain).
PV_PAIRS = (
    (Tissue.BACKGROUND, Tissue.SCALP), (Tissue.SCALP, Tissue.SKULL), (Tissue.SKULL, Tissue.CSF),
    (Tissue.CSF, Tissue.BRAIN),
)
#: Bias-field polynomial degree by default (MRI: Van Leemput et al. 1999 used 4th order; CT: none).
DEFAULT_BIAS_DEGREE = {"mri": 4, "ct": 0}
#: Noise-adaptive edge-preserving smoothing before the EM by default (denoise.py): CT on (brain and
#: CSF differ by ~20-30 HU, comparable to CT noise). MRI off: measured with the edge threshold from
#: the Rician noise of the air (denoise.rayleigh_noise_sd) on the held-out MRI (experiments/results/
#: segmentation_mri_noise.md; minimum Dice brain/CSF/skull/scalp, off -> on), it helps at 8 % noise
#: (2 mm: ANTs 0.972/0.711/0.776/0.950 -> 0.964/0.727/0.854/0.972, MNI152 0.974/0.590/0.833/0.983 ->
#: 0.968/0.656/0.854/0.977; 1 mm: both rows then meet every bar, ANTs skull 0.796 -> 0.902, MNI152
#: CSF 0.677 -> 0.804) and at 2 mm on the MNI152 head at 3 % (CSF 0.669 -> 0.752, meets), but at 1 mm
#: and 3 % it costs CSF (MNI152 0.808 -> 0.677, a met bar lost; ANTs 0.867 -> 0.788). Probably the
#: mechanism measured at 2 mm (not checked per voxel at 1 mm): after smoothing, a flat tissue at high
#: SNR is an intensity spike that a narrow Gaussian of another class can capture. A floor on the
#: Gaussians' width (`noise_floor`, DEFAULT_NOISE_FLOOR) was measured with denoise on (experiments/
#: results/segmentation_mri_varfloor.md): at the smoothing's residual noise it binds nowhere; at the
#: acquisition noise it removes the 1 mm 3 % loss but also every gain above, so no more rows meet.
DEFAULT_DENOISE = {"mri": False, "ct": True}
#: Dirichlet prior on the within-class weights by default (em.map_weights: pseudo-counts of eta times
#: the class's voxels, shared among its free Gaussians, so that no tissue Gaussian of a class is
#: emptied). Off (maximum likelihood) for both: at eta = 0.1 held-out CT Dice moved by < 0.015 either
#: way and MRI CSF on the MNI152 head fell 0.669 -> 0.650 and 0.591 -> 0.559 (a skull Gaussian kept
#: alive on CSF's intensities); experiments/results/segmentation_weight_prior.md.
DEFAULT_WEIGHT_PRIOR = {"mri": 0.0, "ct": 0.0}
#: CT: the M-step keeps the CSF class's first ("pure", lowest-starting) Gaussian at least
#: CSF_BRAIN_MARGIN_HU below the brain class's first (lowest-starting) Gaussian (em.ordered_means).
#: Hounsfield units are physical (water 0, air -1000): CSF is water-like, 0-15 HU, white matter
#: 20-30 HU and grey matter 35-45 HU on any calibrated scanner (Buzug 2008, Computed Tomography,
#: Springer, Fig. 1.2; Schneider, Bortfeld & Schlegel 2000, Phys. Med. Biol. 45:459, Table 1), so a
#: brain Gaussian (grey, white or their mixture) lies >= 20 - 15 = 5 HU above CSF whatever the
#: scanner's offset (an offset moves both). The order only rules out what is physically impossible:
#: a "CSF" Gaussian that climbs onto grey matter where the registered atlas puts CSF on cortex
#: (experiments/results/segmentation_weight_prior.md: maximum likelihood cannot tell the two apart).
#: The margin is the literature's minimum, no more: the fitted "pure" CSF Gaussian absorbs CSF/brain
#: partial volume (ANTs head, 2 mm, 20 HU, default contrast: CSF 26.6 HU against brain 32.4 HU).
#: Measured (experiments/results/segmentation_csf_order.md): held-out ANTs CT random contrast CSF
#: 0.411 -> 0.480 at 20 HU, 0.479 -> 0.494 at 5 HU, brain 0.898 -> 0.919; every other held-out scan,
#: the demo's phantom setting and MRI unchanged; a 10 HU margin gave the same within 0.011.
CSF_BRAIN_MARGIN_HU = 5.0
#: Whether that order is imposed by default (MRI: never; intensities are relative and the order of
#: CSF and brain depends on the weighting).
DEFAULT_CSF_BELOW_BRAIN = {"mri": False, "ct": True}
#: CT: the M-step keeps the CSF class's second Gaussian (its mixture with bone: free Gaussians start at
#: the class's intensity quantiles, so the first is pure CSF, the second the brighter partial volume)
#: at or below the skull class's first (lowest-starting) Gaussian (em.ordered_means;
#: `csf_mix_below_bone`). A voxel the majority rule calls CSF holds less bone than CSF, so its HU lies
#: below the midpoint of CSF and bone; a CSF Gaussian above any of bone's is bone. What the order rules
#: out: on a skull of compact tables (1500-1900 HU) around a diploe (550-850 HU), the CSF class's
#: second Gaussian took the whole diploe as its own and the skull's first sat on CSF: the MNI152 head's
#: CT at 1 mm, held out, CSF 0.000-0.211 and skull 0.39-0.63 on three of its four scans
#: (experiments/results/segmentation_diploe.md, session 21). Measured (held out, minimum Dice CSF):
#: with tables and diploe, 1 mm, MNI152 0.000 -> 0.797-0.850 (skull 1.000), ANTs and phantom within
#: 0.02; 2 mm MNI152 20 HU 0.644 -> 0.651; without a diploe, 2 mm, ANTs 20 HU 0.480 -> 0.421, MNI152
#: 5 HU 0.813 -> 0.750 and the phantom 20 HU 0.663 -> 0.617 (a bar lost: its CSF/bone partial volume
#: sits above the skull's lowest Gaussian).
DEFAULT_CSF_MIX_BELOW_BONE = {"mri": False, "ct": True}
#: MRI: the M-step keeps the skull class's second Gaussian (the diploe's: free Gaussians start at the
#: class's intensity quantiles, so the first is the dark compact tables, the second the brighter
#: marrow) at least DIPLOE_ABOVE_CSF_LOG above the CSF class's first ("pure", darkest) Gaussian, in
#: log intensity (em.ordered_means; `diploe_above_csf`). The physics of a T1-weighted scan: compact
#: bone gives almost no signal (T2* < 1 ms, little free water), so the tables are darker than CSF;
#: the diploe is marrow, mostly fat in an adult calvarium (T1 ~ 250-370 ms at 1.5-3 T against CSF's
#: 3,500-4,500 ms; red marrow ~ 550-600 ms), so it is brighter than CSF on any T1 weighting (Bushberg
#: et al. 2012, The Essential Physics of Medical Imaging, 3rd ed., Table 12-2; Stanisz et al. 2005,
#: Magn. Reson. Med. 54:507, Table 1; Vande Berg et al. 1998, Radiology 208:153 for marrow). A skull
#: Gaussian between the two is partial volume of the tables with CSF or scalp, which the tables'
#: Gaussian widens to cover. What the order rules out is the capture of
#: experiments/results/segmentation_variance_prior.md: a skull Gaussian sitting on pure-CSF
#: intensity where another head's atlas puts skull on this head's CSF, which explains CSF there as
#: well as the CSF class does. The margin log(1.25): the diploe at least a quarter brighter than CSF
#: (fat, red marrow and the phantom's diploe are 1.4-20 times CSF; a quarter leaves room for marrow
#: voxels mixed with the tables). It constrains no tissue a synthetic scan of `templates.render`
#: draws (its skull is one intensity, the tables' Gaussian's, in any order with CSF) and holds for
#: the phantom's MRI (diploe 0.3-0.6, CSF 0.12-0.22 of white matter).
DIPLOE_ABOVE_CSF_LOG = float(np.log(1.25))
#: Whether that order is imposed by default. CT: never (its skull Gaussians are cortical bone and diploe
#: in Hounsfield units, both far above CSF). MRI: off. Measured on the held-out heads (experiments/
#: results/segmentation_mri_capture.md): with two CSF Gaussians it changes nothing (the CSF class's
#: first Gaussian steps below and empties); with one (`gaussians={"csf": 1}`) MNI152 3 % CSF 0.669 ->
#: 0.758 and skull 0.838 -> 0.857 (minimum), ANTs 3 % CSF 0.786 -> 0.807, but MNI152 8 % CSF 0.590 ->
#: 0.557 and the phantom's 3 % scalp 0.783 -> 0.746.
DEFAULT_DIPLOE_ABOVE_CSF = {"mri": False, "ct": False}
#: MRI (T1-weighted): the M-step keeps the CSF class's second Gaussian (free Gaussians start at the
#: class's intensity quantiles: the first is pure CSF, the second the brighter partial volume) at or
#: below the brain class's first (lowest-starting: grey matter and its partial volume) Gaussian, in log
#: intensity (em.ordered_means; `csf_mix_below_brain`). The physics: CSF has the longest T1 of the head's
#: soft tissues (3,500-4,500 ms against grey matter's 1,100-1,800 ms; Stanisz et al. 2005, Magn. Reson.
#: Med. 54:507, Table 1), so on a T1-weighted scan it is darker than grey matter; a voxel the majority rule
#: calls CSF is at least half CSF, and mixed with grey or white matter or bone it stays below grey matter.
#: What the order rules out: on a skull whose marrow is as bright as fat (an adult's, `templates.
#: fatty_marrow`), the CSF class's second Gaussian took the marrow (1.08 of white matter), the skull's
#: Gaussians moved onto the scalp's muscle and fat, and the layers shifted one out (ANTs head, 1 mm, 3 %,
#: held out: skull Dice 0.004; experiments/results/segmentation_diploe.md, session 22).
#: Whether `csf_mix_below_brain` is imposed by default. CT: never (its CSF mixture with bone lies above
#: brain). MRI: on. Measured held out, minimum Dice brain/CSF/skull/scalp (session 22; experiments/results/
#: segmentation_csf_dark_*.md against the tables without it): adult (fatty) marrow, ANTs 3 %, 1 mm
#: 0.972/0.465/0.004/0.736 -> 0.966/0.820/0.787/0.934, 2 mm skull 0.353 -> 0.625; every other real-head
#: scan of the fatty, dark-marrow and marrow-free tables (1 and 2 mm) within 0.016 (MNI152 8 %, 2 mm, CSF
#: 0.782 -> 0.775, still above its bar); own-atlas controls (the demo's phantom setting) unchanged. Cost:
#: the phantom family against the mni152 atlas (no bar met either way), its 3 % seed 1 scan: CSF 0.551 ->
#: 0.051 at 2 mm, 0.759 -> 0.435 at 1 mm (brain 0.93 -> 0.82).
DEFAULT_CSF_MIX_BELOW_BRAIN = {"mri": True, "ct": False}
#: Inverse-gamma prior on each free Gaussian's variance, centred on its class's pooled variance, by
#: default (em.map_variances: worth nu times the class's voxels). Off (maximum likelihood) for both;
#: experiments/results/segmentation_variance_prior.md.
DEFAULT_VARIANCE_PRIOR = {"mri": 0.0, "ct": 0.0}
#: Rounds of warp refinement on the EM's likelihood by default (`refine_warp`; warp_refine.py): 0 = off.
DEFAULT_REFINE_WARP = {"mri": 0, "ct": 0}
#: Most rounds of warp refinement `refine_warp` accepts (each costs a refinement and an EM).
MAX_REFINE_WARP = 5
#: The warp objective sums over every k-th voxel of the EM's sample grid, k = round(this / its voxel):
#: 8x fewer points than the 2 mm sample (SPM samples its objective every 3 mm) at 27 per 12 mm
#: control cell; on the full 2 mm sample a round cost ~55 s per 2 mm head (MNI152 MRI, 60 L-BFGS steps).
WARP_SAMPLE_MM = 4.0
#: Scale s (mm) of the warp refinement's penalty on the displacement change from the registration
#: (warp_refine.py: each component of the change an independent N(0, s^2) per sample voxel;
#: `warp_change_mm`). 4 mm: about one skull thickness (adult calvarium 4-7 mm) and two of the EM's
#: 2 mm sample voxels, i.e. the size of a boundary misplacement the refinement is for (a CSF layer
#: is 2-4 mm thick: a registration that has the inner skull on the CSF is that far off), well below
#: the 14-26 mm rms drift the unpenalised refinement showed (results/segmentation_warp.md). inf: off.
#: Measured (results/segmentation_warp_penalty.md, held-out 2 mm, refine_warp 2): at 4 mm the warp is
#: all but frozen (0.1 mm rms change, tables the default's to +-0.003 but MNI152 MRI 8 % CSF -0.028); the
#: per-voxel prior is ~3.5x stiffer than a per-control-point one of the same s. 32 mm lets MNI152 MRI
#: 3 % meet every bar but costs CT MNI152 20 HU its CSF bar (0.686 -> 0.598), so refine_warp stays off.
DEFAULT_WARP_CHANGE_MM = {"mri": 4.0, "ct": 4.0}
#: MRI `noise_floor` (em.NoiseFloor): the EM's Gaussians kept at least as wide as the *acquisition* noise
#: at their intensity (the log-Rician noise of the scan's measured channel sd),
#: not the residual the smoothing leaves (denoise.log_noise_table(EDGE_FACTOR, DENOISE_STEPS): 0.17 of
#: it in a homogeneous tissue at high SNR, 0.98-1.3 times that table in the pure tissue of the held-out
#: renders, experiments/results/segmentation_mri_varfloor.md). Why the acquisition noise: Perona-Malik
#: conserves the sum of the intensities and the log-likelihood ratio of two equal-variance Gaussians
#: is linear in the data, so with the acquisition variance the evidence a homogeneous region gives for
#: one class over another, summed over its voxels, is what the unsmoothed scan gives; with the residual
#: variance it is 1 / 0.17^2 ~ 35 times that (each raw voxel's noise is shared by ~35 smoothed ones and
#: the EM counts every voxel as independent), so a narrow Gaussian of another class sitting on a flat,
#: smoothed tissue (pure CSF: sd 0.016 in log after smoothing against 0.078 before, MNI152 3 %) outbids
#: the atlas prior and the MRF, which were set against unsmoothed likelihoods (the capture of
#: experiments/results/segmentation_mri_noise.md, section 2). Smoothing still moves each voxel's
#: intensity towards its tissue's (the per-voxel decision), it no longer inflates the evidence.
#: (A floor at the residual noise binds nowhere there: the captured Gaussian, sd 0.017 at 1 mm, is as
#: wide as smoothed pure CSF, so no residual-noise floor can rule it out.)
#: Off by default, also with `denoise`: measured on the held-out MRI with denoise + floor (minimum Dice
#: brain/CSF/skull/scalp), it removes the 1 mm 3 % loss (MNI152 CSF 0.677 -> 0.833, ANTs brain 0.938 ->
#: 0.964) but with it the gains: 1 mm 8 % back to about off (ANTs skull 0.792, MNI152 CSF 0.705: both
#: rows met every bar with denoise alone), 2 mm MNI152 3 % 0.678/0.846 (0.752/0.859, met, with denoise
#: alone). So denoise's 8 % gains came from the same sharper likelihood that costs the 3 % CSF.
DEFAULT_NOISE_FLOOR = {"mri": False, "ct": False}
#: `depth_prior` (depth_prior.py): on for MRI in sessions 14-15. Measured on the held-out MRI (minimum Dice brain/CSF/
#: skull/scalp, experiments/results/segmentation_depth_prior.md): 2 mm MNI152 3 % 0.975/0.669/0.838/
#: 0.968 -> 0.981/0.878/0.906/0.965 (now meets every bar), ANTs 8 % skull 0.776 -> 0.828; 1 mm
#: MNI152 8 % 0.979/0.677/0.875/0.999 -> 0.980/0.777/0.912/0.999 (now meets every bar); no bar met
#: before is lost. The phantom family (no row met before) loses its CSF (2 mm 0.045-0.060 ->
#: 0.002-0.043, 1 mm -> 0.000-0.001): its first EM's brain and scalp are wrong, so its depth is.
#: On CT the bone is hundreds of HU above every other tissue, so the atlas's CSF/skull split is not
#: what fails there, and the depth prior, measured at 2 mm on the ANTs head (before the bone majority
#: rule), costs skull 0.968 -> 0.729 (the refit's CSF Gaussian takes bone partial volume): hence an
#: error with a CT.
#: Session 16: off by default, also for MRI. The layer split (below) learns the CSF/skull split from the
#: scan and replaces the split the depth prior sets; run after the first EM it meets the same bars as
#: after the depth prior (2 mm minimum CSF/skull, ANTs 8 % 0.727/0.858 against 0.739/0.862, MNI152 8 %
#: 0.778/0.895 against 0.789/0.899; experiments/results/segmentation_layer_split.md) and saves the depth
#: prior's EM (6.9 s of the 1 mm benchmark).
DEFAULT_DEPTH_PRIOR = {"mri": False, "ct": False}
#: `layer_split` (depth_prior.fit_layer_split): on for MRI. Measured on the held-out MRI, 2 mm (minimum
#: Dice brain/CSF/skull/scalp, experiments/results/segmentation_layer_split.md): MNI152 8 %
#: 0.974/0.644/0.845/0.981 -> 0.975/0.789/0.899/0.979 (now meets every bar), ANTs 8 %
#: 0.967/0.707/0.828/0.963 -> 0.967/0.735/0.860/0.969, the 3 % rows within -0.006..+0.015. On CT the
#: bone is bright, so intensity alone splits CSF from skull: an error with a CT.
DEFAULT_LAYER_SPLIT = {"mri": True, "ct": False}
#: `scalp_split` (with the layer split, in its EM): an MRI option, off by default (below). The layer split's idea one layer out: along the
#: depth from the segmented brain + CSF to the air outside the head, skull lies inside the scalp, and where an
#: adult's fat-bright marrow meets the scalp's fat only the tables between them tell the two apart; a
#: scanner's point-spread function blurs those 1-2 mm tables until the ray rules of `marrow_inside_skull`
#: (which need them closed) misfire. Session 32 (experiments/results/segmentation_scalp_split.md): the ANTs
#: head with an adult's marrow, 1 mm, neck cut, 3 %, blurred by a PSF of 1.2 mm FWHM (`templates.render`'s
#: `psf_fwhm_mm`): skull / scalp 0.545 / 0.864 -> 0.731 / 0.952; the tables there in that file. Only the tables
#: vote for the change point where marrow and fat look alike, so it is skipped, like the marrow step, on voxels
#: coarser than a table (MARROW_MAX_VOXEL_MM); at 2 mm it cost the no-marrow table a met row (MNI152 8 %: CSF
#: 0.775 -> 0.749). Off by default: it is not general. Session 32's failing case (a synthetic head without
#: marrow whose atlas's skull reaches 2 mm into the scalp's fat, tests/test_segment_marrow.py) was stray brain
#: labels in the fat, which put depth 0 in the scalp (fixed in session 33: the depth starts at the intracranial
#: compartment, `largest_component`). What remains is the estimator's: where an adult's marrow is as bright as
#: the scalp's fat, the fat beyond the outer table votes for whichever side's intensity histogram holds more of
#: it, and that is the skull wherever the scalp is mostly muscle and skin. On nested shells with a 4 mm marrow,
#: 4 mm of fat, 3 of muscle and 2 of skin, started from the true split, it put the change point at the fat's outer
#: edge (skull share of the band 0.58 against 0.33), and in `segment` (layer and scalp split on, labels right
#: before it) skull Dice went 0.995 -> 0.720 (experiments/results/segmentation_scalp_split.md, section 6); on
#: shells whose scalp is all fat it finds the table (tests/test_layer_split.py). So the answer depends on the
#: scalp's make-up, which a new head does not tell us.
DEFAULT_SCALP_SPLIT = {"mri": False, "ct": False}
#: `marrow_inside_skull`: on for MRI. An adult's calvarial marrow is fatty, as bright as the scalp's fat on T1
#: (Simonson & Kao 1992, Pediatr. Radiol. 22:556), so intensity cannot tell it from scalp and a held-out atlas
#: decides. Where that atlas's skull is thinner than the head's, or the registration is pulled inward by the
#: bright marrow (the held-out skull prior at the MNI152 head's marrow: 0.47 without marrow, 0.29 with a
#: fat-bright one; experiments/results/registration_marrow_pull.md), the marrow is labelled scalp, and the
#: skull class, left with the thin tables, drifts onto the CSF. Topology decides instead: scalp lies outside
#: the skull, so scalp-labelled voxels that the segmented skull encloses (`marrow_enclosed`: every one of the 26
#: grid rays meets skull before background that leads out of the grid) are the skull's; their scalp prior moves
#: to skull and the EM runs again, so the skull class learns the marrow's intensity. It needs the tables
#: resolved (MARROW_MAX_VOXEL_MM). Session 24: background that tissue encloses (a compact table as dark as air,
#: labelled background) walls the marrow like the skull instead of letting it out. At 1 mm (same file) the
#: MNI152 head's adult-marrow 8 % scans' skull goes 0.815 -> 0.945 (random contrast: 62k of its table voxels
#: are labelled background) and 0.886 -> 0.923 (default contrast); every other 1 mm scan is unchanged.
#: Session 25, the mirror: once the skull class has a fat-bright Gaussian, scalp fat beside the outer table
#: can be skull too (the ANTs head's 8 % default scan: 231k voxels). Bright skull that the tables (grown by a
#: voxel) do not enclose (`bright_skull_outside_tables`) goes back to the scalp, EM from its own start. At 1 mm
#: (same file, "Session 25", four contrasts per row) the ANTs head's adult-marrow default scans' skull goes
#: 0.798 -> 0.936 (3 %) and 0.713 -> 0.918 (8 %), 14 of 16 real-head scans gain or move by at most 0.005, the
#: scans without marrow or with a child's are unchanged.
#: On CT the skull is bright whatever its marrow (`scalp_outside_skull` is CT's rule for scalp inside the
#: skull): an error with a CT.
DEFAULT_MARROW_INSIDE_SKULL = {"mri": True, "ct": False}
#: Most EM reruns of `marrow_inside_skull` (each about 15 s at 1 mm); a round runs while the newly enclosed
#: voxels are at least MARROW_MIN_SHARE of the skull-labelled ones (MNI152 head, 1 mm, 8 %: 73k, 20k, 5k
#: enclosed in the first three rounds).
MARROW_ROUNDS = 3
#: `csf_inside_tables`: on for MRI since session 27. Where a child's red marrow is as dark as CSF on T1 (the
#: MNI152 head's random contrast 1: CSF 0.38, marrow 0.42 of white matter), the skull class learns the
#: marrow's intensity and takes the CSF beside the brain too (1 mm, 3 %: 352k of 456k CSF voxels labelled
#: skull; the marrow itself is skull). CSF lies inside the inner table, the marrow between the tables:
#: skull-labelled voxels brighter than the tables from which a grid ray reaches the brain or CSF before a wall
#: are CSF (`bright_skull_inside_tables`), where every skull Gaussian is darker than the brain's darkest
#: (`csf_inside_cut`: a fat-bright Gaussian is an adult's marrow, not CSF). Measured on the three 1 mm MRI
#: tables (experiments/results/segmentation_csf_inside_tables.md): child's marrow, MNI152 head CSF
#: 0.298 -> 0.805 (3 %) and 0.286 -> 0.727 (8 %), skull 0.793 -> 0.932 and 0.773 -> 0.881, the 3 % row met;
#: adult marrow over four contrasts: every real-head scan unchanged (ungated, one lost its skull: 0.882 ->
#: 0.384); no marrow: see the write-up. The phantom family's scans move by at most 0.019.
DEFAULT_CSF_INSIDE_TABLES = {"mri": True, "ct": False}
#: `marrow_tables`: MRI. The diploe of a flat skull bone lies between two compact tables (an anatomical given,
#: not a property of one head). A scanner's point-spread function blurs a 1-2 mm table between a fat-bright
#: marrow and CSF or scalp fat into something as dark as CSF and muscle; the EM then gives the inner table to
#: CSF and the outer to the scalp, and the skull class keeps only the marrow (session 33: the MNI152 head, an
#: adult's marrow, 1 mm, 3 %, PSF 1.2 mm FWHM: at depth 0.1-0.2 of the skull 100 % CSF, at 0.8-0.9 94 % scalp,
#: skull Dice 0.761; experiments/results/segmentation_marrow_tables.md). After the EM, voxels labelled CSF or
#: scalp, no brighter than the tables (`tables_cut`), within MARROW_TABLE_MM of the exposed marrow (fat-bright
#: skull with a CSF or scalp face neighbour) are relabelled skull, where the skull class has learnt a fat-bright
#: marrow (`tables_cut` is not None). Measured, 1 mm: the adult-marrow table under a 1.2 mm PSF 0 -> 2 of 4 rows
#: (with the layer split between compartments), the sharp adult-marrow tables (whole head, neck cut) 4 -> 4 with
#: nothing lower than -0.001; without marrow and with a child's it never fired.
DEFAULT_MARROW_TABLES = {"mri": True, "ct": False}
#: `marrow_tables`' reach from the exposed marrow (mm): a compact table's thickness. The phantom draws outer
#: tables of 1.2-2.4 mm and inner ones of 0.8-1.6 mm (jaxhead.phantom), the held-out renders 1.5 mm
#: (templates.DIPLOE_TABLE_MM). Session 33, the MNI152 head rendered with 1.0, 1.5 and 2.0 mm tables (adult's
#: marrow, 3 %, 1 mm; experiments/results/segmentation_marrow_tables.md): under a 1.2 mm FWHM PSF skull
#: 0.761 -> 0.959 (1.5 mm tables) and 0.957 -> 0.979 (2.0 mm); sharp, at most -0.002 (1.0 mm tables: a reach
#: from all of the marrow, not only the exposed, took 1 mm of CSF beyond them there, CSF 0.897 -> 0.858).
MARROW_TABLE_MM = 1.5
#: `marrow_inside_skull` runs only on scans whose coarsest voxel side is at most this (mm): a compact table is
#: 1-2 mm thick (templates.DIPLOE_TABLE_MM: 1.5), and the skull encloses the marrow only where the tables are
#: labelled skull. Measured (experiments/results/segmentation_marrow_inside_skull.md): at 1 mm it gives the
#: MNI152 head's adult-marrow 8 % scan back its skull and CSF (0.306 -> 0.886, 0.311 -> 0.889), raises its
#: random-contrast twin's skull 0.780 -> 0.815, and moves every other real-head scan (no, child's, adult's
#: marrow) by at most 0.012; at 2 mm, where the tables are partial volume with the marrow and the fat, it
#: changed 7 of the 16 real-head scans with marrow by -0.081 to +0.023, the worst the ANTs head's 3 % scan
#: (skull 0.625 -> 0.544: the skull class's fat-bright Gaussian, once learnt, spread into the scalp's fat).
MARROW_MAX_VOXEL_MM = 1.5
#: Below this share of the skull-labelled voxels, scalp voxels the skull encloses are speckle (noise, partial
#: volume), not a marrow layer, and the EM is not run again for them: every extra EM moves a fit, and one run
#: for 3-10 voxels of 10^5 was seen to let the scalp class take the outer table (tests/test_segment_marrow.py).
#: A calvarium's marrow is tens of per cent of its volume (`templates.with_diploe`: 48 % of the ANTs head's
#: skull, 64 % of the MNI152 head's); the MNI152 head's first round at 1 mm, 8 %, moves 73k voxels against
#: about 0.5 million labelled skull.
MARROW_MIN_SHARE = 0.01
#: `marrow_enclosed`: scalp-labelled voxels as dark as compact bone within this distance of the air (through dark
#: voxels) are the skin's partial volume with air, not an outer table (mm; a partial-volume layer is a voxel or
#: two deep). Farther in, they wall the marrow as the skull does. Session 31: geodesic, because a dark piece that
#: touches the air anywhere is not the test: on the MNI152 head cut at the neck (adult marrow, 3 %, 1 mm) the
#: outer table the scalp class took joins the air somewhere, and with whole pieces the marrow found nothing.
#: Measured (experiments/results/segmentation_dark_wall.md): the adult-marrow 1 mm table with the neck cut, rows
#: meeting every bar 2 -> 4 of 6 (the MNI152 head's skull 0.229-0.554 -> 0.859-0.996); the 1 mm tables of
#: adult's, child's and no marrow on whole heads moved by at most 0.003.
SKIN_LAYER_MM = 2.0
#: the neighbourhood that shares one CSF/skull change point (Gaussian window sd, mm) and the width (in
#: normalised depth) of the prior's step at it. Measured at 2 mm (same file): window 4 / 6 / 8 / 12 mm
#: gives the 8 % CSF minima 0.734 / 0.735 / 0.731 / 0.713 (ANTs) and 0.792 / 0.789 / 0.774 / 0.739
#: (MNI152); width 0.05 and 0.1 within 0.01 of each other (the same file). 6 mm: the middle of the flat range.
LAYER_SPLIT_MM = 6.0
LAYER_SPLIT_WIDTH = 0.1
#: `unmodelled_start`: the first EM's skull/scalp shares where the atlas models no bone (face, neck).
#: "atlas": the atlas's placeholder soft tissue; "equal": equal shares. Measured at 2 mm on the ANTs
#: head with the mni152 atlas (skull share of skull + scalp there, truth-weighted by the map: 0.106-0.108;
#: experiments/results/segmentation_unmodelled_start.md): MRI "atlas" learns 0.017-0.075, always below,
#: because in T1 bone is as dark as the air/skin partial volume that a scalp Gaussian must model, so
#: with all the region's prior on scalp that Gaussian also takes the face's bone; "equal" learns
#: 0.088-0.148, and the 1 mm MRI 8 % skull Dice goes 0.807 -> 0.919. On CT bone is hundreds of HU above
#: soft tissue: "atlas" learns 0.132-0.142, "equal" over-estimates (0.172-0.184) and costs skull and CSF
#: Dice (2 mm minimum skull 0.985 -> 0.973, CSF 0.480 -> 0.425).
#: "checked" (session 35): "equal"; where the skull share it learns is above the equal start, a second first
#: EM from it; if that learns a larger share still, the share is running away (the skull class is taking a tissue
#: the region is mostly made of: under a scanner's blur an adult's fat-bright marrow takes the face's fat, 0.60 ->
#: 0.88 -> 0.98, truth 0.11), and the first EM from the atlas's placeholder is used instead (`checked_start`;
#: experiments/results/segmentation_unmodelled_runaway.md).
DEFAULT_UNMODELLED_START = {"mri": "checked", "ct": "atlas"}
UNMODELLED_STARTS = ("equal", "atlas", "checked")
#: Perona-Malik edge threshold in noise sd (k = EDGE_FACTOR * noise_sd) and steps (denoise.py).
EDGE_FACTOR = 2.0
DENOISE_STEPS = 5


def _per_class(value, name: str) -> tuple[int, ...] | None:
    if value is None:
        return None
    if not isinstance(value, Mapping):
        raise ValueError(
            f"[segment] `{name}` must be a mapping of tissue name -> count, e.g. {{'brain': 2}}, got {value!r}."
        )
    out = {}
    for k, v in value.items():
        try:
            t = Tissue.parse(k)
        except ValueError as err:
            raise ValueError(f"[segment] `{name}`: {err}") from None
        if isinstance(v, bool) or not isinstance(v, (int, np.integer)) or v < 1:
            raise ValueError(f"[segment] `{name}[{k!r}]` must be an integer >= 1, got {v!r}.")
        out[int(t)] = int(v)
    return tuple(out.get(k, -1) for k in range(N_CLASSES))


def _check_optional_bool(name: str, value) -> None:
    """A ValueError unless a SegmentConfig switch is true, false or None (the modality default)."""
    if value is not None and not isinstance(value, (bool, np.bool_)):
        raise ValueError(f"[segment] `{name}` must be true, false or None (modality default), got {value!r}.")


def _check_modality_switch(name: str, value, modality: str, needs: str, reason: str) -> None:
    """`_check_optional_bool`, and a ValueError when a switch that only one modality has is turned on for
    the other (`reason`: why it needs `needs`, in the message)."""
    _check_optional_bool(name, value)
    if value and modality != needs:
        other = "an MRI" if needs == "ct" else "a CT"
        raise ValueError(f"[segment] `{name}=True` needs modality='{needs}' {reason} Leave it None for {other}.")


@dataclass(frozen=True, kw_only=True)
class SegmentConfig:
    """Settings of `segment`.

    Arguments:
        modality: "mri" (T1-like, arbitrary units, bias field) or "ct" (Hounsfield units).
        register: RegisterConfig of the atlas-to-scan registration.
        gaussians: free Gaussians per class, keyed by tissue name ("background", "brain", "csf", "skull",
            "scalp") or Tissue; missing classes take the modality default (DEFAULT_GAUSSIANS, or
            DEFAULT_GAUSSIANS_PV with partial-volume Gaussians).
        partial_volume: add two tied partial-volume Gaussians per pair of bordering layers (PV_PAIRS),
            so that a boundary voxel is labelled with the tissue that fills more than half of it
            (the tissue at its centre); see jaxhead.segmentation.em. Off by default (see
            DEFAULT_GAUSSIANS_PV for what it gains and loses).
        beta: Potts MRF strength (mean field over 6 neighbours; 0 = off).
        relax: prior relaxation weight a in [0, 1) (Cardoso et al. 2011; NiftySeg recommends 0.5).
        relax_sigma_mm: Gaussian smoothing of the posterior in the relaxed prior, mm.
        bias_degree: MRI bias field polynomial degree (None: modality default, 4 for MRI, 0 for CT).
        max_iter: EM iterations at most.
        tol: EM stops when the mean log-likelihood per voxel (standardised intensities) changes by
            less than this (nats).
        em_sample_mm: the EM estimates its parameters on every k-th voxel along each axis, k this over the
            voxel size rounded, at least 1 (`sample_stride`): every 2nd voxel at 1 mm, every voxel at 2 mm.
            3 mm (SPM's sampling distance) halves the EM's cost at 1 mm but was measured to cost a met row
            (experiments/results/segmentation_em_sample.md).
        first_pass_sample_mm: the same for `classify`'s first EM where the atlas models no bone (`unmodelled`):
            that EM only gives the region's skull/scalp proportions (a regional average over 10^5-10^6 voxels);
            the second EM, on `em_sample_mm`, starts afresh, not from where the first stopped. At least
            `em_sample_mm`. When the second EM started from the first's end point, 4 and 3 mm each lost a met
            row, so until session 30 the default was 2 mm (experiments/results/segmentation_first_pass.md).
        sweeps: mean-field sweeps on the full grid after an EM on a strided sample of it.
        precision: "float32" (default, see module docstring) or "float64".
        atlas: the default atlas used when `segment` gets none: "mni152" (real anatomy: the ICBM
            2009a MNI152 brain in fsaverage's inner skull and scalp; see templates.py) or "phantom"
            (jaxhead's synthetic heads: tests, the synthetic demo).
        atlas_voxel_mm, atlas_subjects: voxel size of that atlas; phantom subjects it averages.
        denoise: smooth the scan by Perona-Malik diffusion with an edge threshold of EDGE_FACTOR times
            its estimated noise sd before the EM (`jaxhead.segmentation.denoise`; self-limiting: a
            noise-free scan is unchanged). None: the modality default (DEFAULT_DENOISE).
        weight_prior: eta of the Dirichlet (MAP) prior on each class's within-class weights
            (`jaxhead.segmentation.em.map_weights`); 0 = maximum likelihood; None: the modality
            default (DEFAULT_WEIGHT_PRIOR).
        csf_below_brain: CT: keep the CSF class's first Gaussian mean CSF_BRAIN_MARGIN_HU below the
            brain class's first Gaussian mean (literature Hounsfield units; em.ordered_means). None: the
            modality default (DEFAULT_CSF_BELOW_BRAIN); True with an MRI is an error.
        csf_mix_below_bone: CT: keep the CSF class's second Gaussian mean (its mixture with bone) at or
            below the skull class's first (em.ordered_means; DEFAULT_CSF_MIX_BELOW_BONE). Needs >= 2 free
            CSF Gaussians. None: the modality default (on for CT); True with an MRI is an error.
        csf_mix_below_brain: MRI (T1-weighted): keep the CSF class's second Gaussian mean at or below the
            brain class's first (T1 physics: CSF darker than grey matter; em.ordered_means). Needs >= 2
            free CSF Gaussians. None: the modality default (DEFAULT_CSF_MIX_BELOW_BRAIN: on for MRI;
            skipped where the CSF class has one Gaussian); True with a CT is an error.
        diploe_above_csf: MRI: keep the skull class's second Gaussian mean DIPLOE_ABOVE_CSF_LOG (log
            intensity) above the CSF class's first Gaussian mean (T1 physics: fatty marrow brighter than
            CSF; em.ordered_means). Needs >= 2 free skull Gaussians. None: the modality default
            (DEFAULT_DIPLOE_ABOVE_CSF); True with a CT is an error.
        variance_prior: nu of the inverse-gamma (MAP) prior on each free Gaussian's variance, centred on
            its class's pooled variance (`jaxhead.segmentation.em.map_variances`); 0 = maximum
            likelihood; None: the modality default (DEFAULT_VARIANCE_PRIOR).
        bone_majority: CT: relabel the bone surface by the partial-volume majority rule after the EM
            (`bone_majority`; ignored for MRI).
        air_majority: CT: relabel the skin's partial-volume shell (scalp voxels mostly air) by the
            majority rule after the EM (`air_majority`; ignored for MRI).
        scalp_outside_skull: CT: after the majority rules, scalp that the segmented skull encloses on
            every side and that lies beside the brain or CSF goes to its next most probable class
            (`scalp_outside_skull`; ignored for MRI, whose skull is not reliable enough to enclose).
        refine_warp: after the EM, refine the atlas's B-spline warp on the EM's mixture likelihood and
            re-run the EM on the re-warped priors, at most this many times (stopping when a refinement
            raises the objective by less than `tol`; SPM's unified segmentation, see
            `jaxhead.segmentation.warp_refine`); 0 = off; None: the modality default
            (DEFAULT_REFINE_WARP). Needs the registration's B-spline stage.
        warp_change_mm: scale s (mm, > 0) of the refinement's Gaussian penalty on the displacement's
            change from the registration's (`jaxhead.segmentation.warp_refine`); inf: no penalty (the
            bending energy alone); None: the modality default (DEFAULT_WARP_CHANGE_MM).
        noise_floor: MRI: keep every Gaussian at least as wide as the acquisition noise of a tissue of
            its intensity (the log of the scan's Rician noise, measured from the air by
            `denoise.rayleigh_noise_sd`; `_noise_floor`, em.NoiseFloor), also after `denoise` (why: the
            comment of DEFAULT_NOISE_FLOOR), so no Gaussian of one class can claim a smoothed,
            texture-free tissue of another with a likelihood sharper than the scan's noise allows.
            None: the modality default (DEFAULT_NOISE_FLOOR: off); True with a CT is an error (CT
            noise is not Rician; not measured).
        depth_prior: MRI: after the EM, share each voxel's CSF + skull prior by the atlas's p(CSF | t), t
            the voxel's normalised depth between the segmented brain and scalp, and run the EM again
            (`jaxhead.segmentation.depth_prior`: the band's boundaries are seen on T1, its CSF/skull
            split is not). None: the modality default (DEFAULT_DEPTH_PRIOR: off; `layer_split` learns
            the split from the scan instead); True with a CT is an error.
        layer_split: MRI: after the EM (and the depth prior where it is on), learn the CSF/skull change point in depth
            between the segmented brain and scalp from the scan's own intensities, per neighbourhood
            (`depth_prior.fit_layer_split`: CSF inside the skull; LAYER_SPLIT_MM), share each voxel's
            CSF + skull prior by a step at it (`depth_prior.with_local_split`) and run the EM again.
            None: the modality default (DEFAULT_LAYER_SPLIT: on for MRI); True with a CT is an error.
        scalp_split: MRI, with `layer_split`: also learn the skull/scalp change point in depth between the
            segmented brain + CSF and the air outside the head the same way (skull inside the scalp), and share
            each voxel's skull + scalp prior by a step at it in the same EM (`_layer_split`); skipped, and said so
            in the report, on voxels coarser than MARROW_MAX_VOXEL_MM. None: the modality default
            (DEFAULT_SCALP_SPLIT: off); True with a CT, or without the layer split, is an error.
        marrow_inside_skull: MRI: after the EM (and the depth prior), before the layer split, scalp-labelled
            voxels that the segmented skull encloses (`marrow_enclosed`; scalp as dark as the tables, deeper than
            SKIN_LAYER_MM, walls the marrow like the skull) get the skull's prior and the EM runs
            again, up to MARROW_ROUNDS times (DEFAULT_MARROW_INSIDE_SKULL's comment: an adult's marrow is
            as bright as fat); skipped, and said so in the report, on voxels coarser than
            MARROW_MAX_VOXEL_MM. None: the modality default (on for MRI); True with a CT is an error.
        csf_inside_tables: MRI: after the marrow step and again after the layer split, skull-labelled voxels
            brighter than the skull's tables from which a grid ray reaches the brain or CSF before a wall
            (`bright_skull_inside_tables`: CSF the skull class took with a marrow as dark as CSF) get the
            CSF's prior and the EM runs again, where every skull Gaussian is darker than the brain's darkest
            (`csf_inside_cut`); skipped on voxels coarser than MARROW_MAX_VOXEL_MM. None: the modality
            default (DEFAULT_CSF_INSIDE_TABLES: on for MRI); True with a CT is an error.
        marrow_tables: MRI: after the EM (the last step before the labels), voxels labelled CSF or scalp, no
            brighter than the skull's tables, within MARROW_TABLE_MM of the skull's exposed fat-bright marrow are
            relabelled skull (`marrow_tables`: the compact tables a scanner's blur gave to the neighbours), where
            the skull class has learnt a fat-bright marrow; counted in the report, skipped on voxels coarser than
            MARROW_MAX_VOXEL_MM. None: the modality default (DEFAULT_MARROW_TABLES); True with a CT is an error.
        unmodelled_start: where the atlas models no bone (`Atlas.unmodelled`: the mni152 atlas's face
            and neck), the skull and scalp shares the first EM starts from, before their proportions
            are learnt from the scan (`classify`): "equal" (half each), "atlas" (the atlas's
            placeholder soft tissue) or "checked" ("equal", falling back to "atlas" where the skull
            share learnt rose above half and a second first EM from it raises it further: a runaway,
            `checked_start`). None: the modality default (DEFAULT_UNMODELLED_START: "checked" for MRI,
            "atlas" for CT; why: its comment).
        check_registration: raise when the atlas registration ends implausibly (a flip, a scale
            outside MIN_SCALE..MAX_SCALE, a rotation over MAX_ROTATION_DEG, similarity below
            MIN_NMI): the scan is most likely mis-oriented (see `check_registration`).
    """

    modality: Literal["mri", "ct"] = "mri"
    register: RegisterConfig = field(default_factory=RegisterConfig)
    gaussians: Mapping | None = None
    partial_volume: bool = False
    beta: float = 0.4
    relax: float = 0.5
    relax_sigma_mm: float = 2.0
    bias_degree: int | None = None
    max_iter: int = 50
    tol: float = 1e-4
    em_sample_mm: float = 2.0
    first_pass_sample_mm: float = 4.0
    sweeps: int = 3
    precision: Literal["float32", "float64"] = "float32"
    atlas: Literal["mni152", "phantom"] = "mni152"
    atlas_voxel_mm: float = 2.0
    atlas_subjects: int = 8
    check_registration: bool = True
    bone_majority: bool = True
    air_majority: bool = True
    scalp_outside_skull: bool = True
    denoise: bool | None = None
    weight_prior: float | None = None
    csf_below_brain: bool | None = None
    variance_prior: float | None = None
    csf_mix_below_bone: bool | None = None
    csf_mix_below_brain: bool | None = None
    diploe_above_csf: bool | None = None
    refine_warp: int | None = None
    warp_change_mm: float | None = None
    noise_floor: bool | None = None
    depth_prior: bool | None = None
    layer_split: bool | None = None
    scalp_split: bool | None = None
    marrow_inside_skull: bool | None = None
    csf_inside_tables: bool | None = None
    marrow_tables: bool | None = None
    unmodelled_start: Literal["equal", "atlas", "checked"] | None = None

    def __post_init__(self):
        if not isinstance(self.modality, str) or self.modality not in ("mri", "ct"):
            raise ValueError(f"[segment] `modality` must be 'mri' or 'ct', got {self.modality!r}.")
        if not isinstance(self.register, RegisterConfig):
            raise ValueError(f"[segment] `register` must be a RegisterConfig, got {type(self.register).__name__}.")
        _per_class(self.gaussians, "gaussians")
        if not isinstance(self.partial_volume, (bool, np.bool_)):
            raise ValueError(f"[segment] `partial_volume` must be true or false, got {self.partial_volume!r}.")
        if not self.beta >= 0:
            raise ValueError(f"[segment] `beta` must be >= 0, got {self.beta}.")
        if not 0 <= self.relax < 1:
            raise ValueError(f"[segment] `relax` must be in [0, 1), got {self.relax}.")
        if not self.relax_sigma_mm > 0:
            raise ValueError(f"[segment] `relax_sigma_mm` must be > 0, got {self.relax_sigma_mm}.")
        if self.bias_degree is not None and not (0 <= self.bias_degree <= 8):
            raise ValueError(f"[segment] `bias_degree` must be in 0..8 or None, got {self.bias_degree}.")
        if self.max_iter < 1:
            raise ValueError(f"[segment] `max_iter` must be >= 1, got {self.max_iter}.")
        if not self.tol > 0:
            raise ValueError(f"[segment] `tol` must be > 0, got {self.tol}.")
        if not self.em_sample_mm > 0:
            raise ValueError(f"[segment] `em_sample_mm` must be > 0, got {self.em_sample_mm}.")
        if not self.first_pass_sample_mm > 0:
            raise ValueError(f"[segment] `first_pass_sample_mm` must be > 0, got {self.first_pass_sample_mm}.")
        if self.sweeps < 0:
            raise ValueError(f"[segment] `sweeps` must be >= 0, got {self.sweeps}.")
        if self.precision not in ("float32", "float64"):
            raise ValueError(f"[segment] `precision` must be 'float32' or 'float64', got {self.precision!r}.")
        check_atlas_kind(self.atlas, "[segment] atlas")
        for name in ("bone_majority", "air_majority", "scalp_outside_skull"):
            if not isinstance(getattr(self, name), (bool, np.bool_)):
                raise ValueError(f"[segment] `{name}` must be true or false, got {getattr(self, name)!r}.")
        _check_optional_bool("denoise", self.denoise)
        if self.weight_prior is not None and not (isinstance(self.weight_prior, (int, float)) and self.weight_prior >= 0):
            raise ValueError(
                f"[segment] `weight_prior` must be a number >= 0 (0 = maximum likelihood) or None (modality "
                f"default), got {self.weight_prior!r}."
            )
        _check_modality_switch("csf_below_brain", self.csf_below_brain, self.modality, "ct",
                               "(Hounsfield units); MRI intensities are relative and their CSF/brain order "
                               "depends on the weighting.")
        _check_modality_switch("csf_mix_below_bone", self.csf_mix_below_bone, self.modality, "ct",
                               "(Hounsfield units); on MRI bone is dark and CSF's mixtures with it are darker "
                               "than CSF.")
        self._check_second_gaussian("csf_mix_below_bone", self.csf_mix_below_bone, Tissue.CSF, "CSF, its bone mixture")
        _check_modality_switch("csf_mix_below_brain", self.csf_mix_below_brain, self.modality, "mri",
                               "(a T1-weighted log intensity order); on CT the CSF class's second Gaussian is "
                               "its mixture with bone, above brain.")
        self._check_second_gaussian("csf_mix_below_brain", self.csf_mix_below_brain, Tissue.CSF,
                                    "CSF, its partial volume")
        _check_modality_switch("diploe_above_csf", self.diploe_above_csf, self.modality, "mri",
                               "(a T1-weighted log intensity order); in CT both skull Gaussians lie hundreds of "
                               "HU above CSF.")
        self._check_second_gaussian("diploe_above_csf", self.diploe_above_csf, Tissue.SKULL, "tables, diploe")
        if self.variance_prior is not None and not (
                isinstance(self.variance_prior, (int, float)) and not isinstance(self.variance_prior, bool)
                and self.variance_prior >= 0):
            raise ValueError(
                f"[segment] `variance_prior` must be a number >= 0 (0 = maximum likelihood) or None (modality "
                f"default), got {self.variance_prior!r}."
            )
        if self.refine_warp is not None and (
                isinstance(self.refine_warp, bool) or not isinstance(self.refine_warp, (int, np.integer))
                or not 0 <= self.refine_warp <= MAX_REFINE_WARP):
            raise ValueError(
                f"[segment] `refine_warp` must be an integer 0..{MAX_REFINE_WARP} (rounds of warp refinement; 0 = off) "
                f"or None (modality default), got {self.refine_warp!r}."
            )
        if self.warp_change_mm is not None and (
                isinstance(self.warp_change_mm, bool) or not isinstance(self.warp_change_mm, (int, float, np.number))
                or not self.warp_change_mm > 0):
            raise ValueError(
                f"[segment] `warp_change_mm` must be a number > 0 (mm: the scale of the warp refinement's penalty on "
                f"the displacement change; inf = no penalty) or None (modality default), got {self.warp_change_mm!r}."
            )
        if self.refine_rounds() > 0 and not self.register.bspline:
            raise ValueError(
                f"[segment] `refine_warp={self.refine_rounds()}` refines the registration's B-spline warp, but "
                "`register.bspline` is off; turn the B-spline stage on or set refine_warp=0."
            )
        _check_modality_switch("noise_floor", self.noise_floor, self.modality, "mri",
                               "(its floor is the log of Rician noise); a CT's noise floor is not modelled.")
        _check_modality_switch("depth_prior", self.depth_prior, self.modality, "mri",
                               "(T1: CSF and bone both dark); on CT the bone is bright and the depth prior was "
                               "measured to cost skull Dice.")
        _check_modality_switch("layer_split", self.layer_split, self.modality, "mri",
                               "(T1: CSF and bone both dark); on CT the bone is bright, so the intensities "
                               "split CSF from skull without it.")
        _check_modality_switch("scalp_split", self.scalp_split, self.modality, "mri",
                               "(T1: an adult's marrow as bright as the scalp's fat); on CT the bone is bright.")
        if self.scalp_split and not self.layer_split_on():
            raise ValueError("[segment] `scalp_split` = true needs the layer split (it runs in the layer split's EM); "
                             "set layer_split = true, or leave scalp_split unset.")
        _check_modality_switch("marrow_inside_skull", self.marrow_inside_skull, self.modality, "mri",
                               "(T1: fatty marrow as bright as the scalp's fat); on CT the bone is bright and "
                               "`scalp_outside_skull` relabels scalp inside the skull.")
        _check_modality_switch("csf_inside_tables", self.csf_inside_tables, self.modality, "mri",
                               "(T1: a marrow as dark as CSF); on CT the bone is bright.")
        _check_modality_switch("marrow_tables", self.marrow_tables, self.modality, "mri",
                               "(T1: compact tables as dark as CSF beside a fat-bright marrow); on CT the bone is "
                               "bright and `bone_majority` draws its surface.")
        if self.unmodelled_start is not None and self.unmodelled_start not in UNMODELLED_STARTS:
            raise ValueError(
                f"[segment] `unmodelled_start` must be one of {UNMODELLED_STARTS} (the first EM's skull/scalp "
                f"shares where the atlas models no bone) or None (modality default), got {self.unmodelled_start!r}."
            )
        if not isinstance(self.check_registration, (bool, np.bool_)):
            raise ValueError(f"[segment] `check_registration` must be true or false, got {self.check_registration!r}.")
        if not self.atlas_voxel_mm > 0 or self.atlas_subjects < 1:
            raise ValueError("[segment] `atlas_voxel_mm` must be > 0 and `atlas_subjects` >= 1.")

    def _check_second_gaussian(self, name: str, on, cls: Tissue, what: str) -> None:
        """An order on class `cls`'s second Gaussian needs two free ones (`gaussians`, `partial_volume`)."""
        n = self.gaussians_per_class()[int(cls)]
        label = "CSF" if cls == Tissue.CSF else cls.name.lower()
        if on and n < 2:
            raise ValueError(
                f"[segment] `{name}=True` orders the {label} class's second Gaussian, but it has {n} free "
                f"Gaussian(s) (`gaussians`, `partial_volume`); give it >= 2 ({what}) or leave the order off."
            )

    def warp_change_scale(self) -> float:
        """Scale (mm) of the warp refinement's displacement-change penalty (`warp_change_mm`, or the default)."""
        return DEFAULT_WARP_CHANGE_MM[self.modality] if self.warp_change_mm is None else float(self.warp_change_mm)

    def depth_prior_on(self) -> bool:
        """Whether the CSF/skull priors follow depth (`depth_prior`, or the modality default)."""
        return DEFAULT_DEPTH_PRIOR[self.modality] if self.depth_prior is None else bool(self.depth_prior)

    def layer_split_on(self) -> bool:
        """Whether the CSF/skull split is learnt from the scan (`layer_split`, or the modality default)."""
        return DEFAULT_LAYER_SPLIT[self.modality] if self.layer_split is None else bool(self.layer_split)

    def scalp_split_on(self) -> bool:
        """Whether the skull/scalp split is learnt with the layer split (`scalp_split`, or the modality default)."""
        if not self.layer_split_on():
            return False
        return DEFAULT_SCALP_SPLIT[self.modality] if self.scalp_split is None else bool(self.scalp_split)

    def csf_inside_tables_on(self) -> bool:
        """Whether bright skull inside the tables goes to CSF (`csf_inside_tables`, or the modality default)."""
        if self.csf_inside_tables is None:
            return DEFAULT_CSF_INSIDE_TABLES[self.modality]
        return bool(self.csf_inside_tables)

    def marrow_tables_on(self) -> bool:
        """Whether the tables around a fat-bright marrow are relabelled skull (`marrow_tables`, or the default)."""
        if self.marrow_tables is None:
            return DEFAULT_MARROW_TABLES[self.modality]
        return bool(self.marrow_tables)

    def marrow_inside_skull_on(self) -> bool:
        """Whether scalp the skull encloses is given to the skull (`marrow_inside_skull`, or the modality default)."""
        if self.marrow_inside_skull is None:
            return DEFAULT_MARROW_INSIDE_SKULL[self.modality]
        return bool(self.marrow_inside_skull)

    def first_pass_sample_of(self) -> float:
        """The first EM's sampling distance where the atlas models no bone (`first_pass_sample_mm`, at least
        `em_sample_mm`), mm."""
        return max(self.first_pass_sample_mm, self.em_sample_mm)

    def unmodelled_start_of(self) -> str:
        """The first EM's shares where the atlas models no bone (`unmodelled_start`, or the modality default)."""
        return DEFAULT_UNMODELLED_START[self.modality] if self.unmodelled_start is None else self.unmodelled_start

    def refine_rounds(self) -> int:
        """Rounds of warp refinement (`refine_warp`, or the modality default)."""
        return DEFAULT_REFINE_WARP[self.modality] if self.refine_warp is None else int(self.refine_warp)

    def gaussians_per_class(self) -> tuple[int, ...]:
        """Free Gaussians per class, ordered BACKGROUND, BRAIN, CSF, SKULL, SCALP (without the tied
        partial-volume ones)."""
        base = (DEFAULT_GAUSSIANS_PV if self.partial_volume else DEFAULT_GAUSSIANS)[self.modality]
        given = _per_class(self.gaussians, "gaussians")
        if given is None:
            return base
        return tuple(g if g > 0 else b for g, b in zip(given, base))

    def em_options(self, relax_sigma_vox: float) -> EMOptions:
        """The EMOptions this config implies (relaxation width in voxels of the EM grid)."""
        counts = self.gaussians_per_class()
        cc, pv = [], []
        for k, n in enumerate(counts):
            cc += [k] * n
            pv += [-1] * n
            if self.partial_volume:
                for a, b in PV_PAIRS:
                    if k in (a, b):
                        cc.append(k)
                        pv.append(int(b if k == a else a))
        degree = DEFAULT_BIAS_DEGREE[self.modality] if self.bias_degree is None else self.bias_degree
        eta = DEFAULT_WEIGHT_PRIOR[self.modality] if self.weight_prior is None else self.weight_prior
        below = DEFAULT_CSF_BELOW_BRAIN[self.modality] if self.csf_below_brain is None else self.csf_below_brain
        order = ((cc.index(int(Tissue.CSF)), cc.index(int(Tissue.BRAIN)), CSF_BRAIN_MARGIN_HU),) if below else ()
        mix = DEFAULT_CSF_MIX_BELOW_BONE[self.modality] if self.csf_mix_below_bone is None else self.csf_mix_below_bone
        if mix and counts[int(Tissue.CSF)] >= 2:  # the default is skipped where the CSF class has one Gaussian
            order += ((cc.index(int(Tissue.CSF)) + 1, cc.index(int(Tissue.SKULL)), 0.0),)
        dark = (DEFAULT_CSF_MIX_BELOW_BRAIN[self.modality] if self.csf_mix_below_brain is None
                else self.csf_mix_below_brain)
        if dark and counts[int(Tissue.CSF)] >= 2:  # as for the bone mixture: skipped with one CSF Gaussian
            order += ((cc.index(int(Tissue.CSF)) + 1, cc.index(int(Tissue.BRAIN)), 0.0),)
        diploe = DEFAULT_DIPLOE_ABOVE_CSF[self.modality] if self.diploe_above_csf is None else self.diploe_above_csf
        if diploe:  # the skull's free Gaussians come first in its group, tables then diploe
            order += ((cc.index(int(Tissue.CSF)), cc.index(int(Tissue.SKULL)) + 1, DIPLOE_ABOVE_CSF_LOG),)
        nu = DEFAULT_VARIANCE_PRIOR[self.modality] if self.variance_prior is None else self.variance_prior
        return EMOptions(
            component_class=tuple(cc), n_classes=N_CLASSES, beta=float(self.beta), max_iter=self.max_iter,
            tol=float(self.tol), relax=float(self.relax), relax_sigma_vox=float(relax_sigma_vox),
            bias_degree=int(degree), bias_classes=tuple(range(1, N_CLASSES)),
            pv_of=tuple(pv) if self.partial_volume else (), pv_log=self.modality == "mri", weight_prior=float(eta),
            mean_order=order,
            variance_prior=float(nu),
        )


class Segmentation(eqx.Module):
    """The report of `segment_reported`: the fitted tissue model behind the labels.

    Arguments:
        labels: the same LabelMap of Tissue values (BACKGROUND, BRAIN, CSF, SKULL, SCALP) on the scan's grid.
        posteriors: (5, x, y, z) float32 class posteriors, ordered as Tissue values.
        transform: the atlas registration (scan mm -> atlas mm).
        params: fitted Gaussian mixture (means/variances in log intensity for MRI, HU for CT).
        component_class: the class of each Gaussian.
        bias_field: (x, y, z) MRI: the multiplicative bias field exp(b) (scan = bias * true image);
            CT: the additive field in HU (zeros unless cfg.bias_degree > 0).
        n_iter: EM iterations.
        converged: whether the EM met its tolerance.
        atlas_name: the atlas used (`Atlas.name`: "mni152", "phantom", ...), for the run report.
        registration: plausibility figures of the affine registration (`registration_summary`):
            scales, rotation (deg), determinant, NMI after the affine stage; and what the later steps
            did, each under its own key where it ran: "unmodelled" (the start and the learnt skull and scalp
            shares where the atlas models no bone), "warp_refinement", "depth_prior" (MRI),
            "marrow_inside_skull" (MRI: rounds, voxels given to the skull per round), "layer_split" (MRI; its
            "scalp_split" inside it),
            "bone_majority", "air_majority" and "scalp_outside_skull" (CT: thresholds and voxels
            relabelled).
    """

    labels: LabelMap
    posteriors: np.ndarray
    transform: Transform
    params: MixtureParams
    component_class: tuple[int, ...] = eqx.field(static=True)
    bias_field: np.ndarray
    n_iter: int = eqx.field(static=True)
    converged: bool = eqx.field(static=True)
    atlas_name: str = eqx.field(static=True, default="custom")
    registration: dict = eqx.field(static=True, default_factory=dict)


#: CT: voxels below this many HU are a scanner's padding (outside its reconstruction circle, or a
#: DICOM pixel-padding value: -2048, -3024, -32768 on common scanners), not air: air is -1000 HU, and
#: its noise (sd up to ~100 HU on a low-dose scan; 36-57 HU in the air of our 20 HU renderings, whose
#: lowest voxels reach -1105) and a scanner's calibration offset (tens of HU) stay well above.
CT_PADDING_BELOW_HU = -1500.0


def replace_ct_padding(volume: Volume) -> tuple[Volume, dict]:
    """CT: the scan with its padding (voxels below CT_PADDING_BELOW_HU) set to the scan's own air level
    (the median of the voxels between CT_PADDING_BELOW_HU and -500 HU; -1000 if there are none).

    Why: padding is background, but a value thousands of HU below the air stretches the intensity
    range that the EM's variance floor and the registration's histogram are scaled by (measured on the
    ANTs head, 2 mm, 10 HU, a -3024 HU circle clipping 12 % of the grid and no head voxel: CSF Dice
    0.670 -> 0.488 left as it is; experiments/results/segmentation_air_majority.md).

    Returns:
        (volume, report): the input itself and {} when there is no padding; otherwise a new Volume and
        {"voxels": how many were replaced, "lowest_hu": their lowest value, "air_hu": the level set}.
    """
    d = np.asarray(volume.data)
    pad = d < CT_PADDING_BELOW_HU
    if not pad.any():
        return volume, {}
    air = d[~pad & (d < -500.0)]
    level = float(np.median(air)) if air.size else -1000.0
    info = dict(voxels=int(pad.sum()), lowest_hu=float(d.min()), air_hu=level)
    return Volume(np.where(pad, level, d), volume.affine), info


def _check_inputs(volume, atlas, cfg):
    if not isinstance(cfg, SegmentConfig):
        raise ValueError(f"`cfg` must be a SegmentConfig, got {type(cfg).__name__}.")
    if not isinstance(volume, Volume):
        raise ValueError(f"`volume` must be a jaxhead Volume, got {type(volume).__name__}; load it with load_volume.")
    d = volume.data
    if np.ptp(d) == 0:
        raise ValueError(
            f"`volume` is constant (every voxel = {float(d.flat[0])}); there is nothing to segment. "
            "Check that the scan loaded correctly."
        )
    if min(volume.shape) < 8:
        raise ValueError(f"`volume` has shape {volume.shape}; segmentation needs >= 8 voxels per axis.")
    air_hu = np.mean(d < -500)
    if cfg.modality == "mri" and air_hu > 0.05:
        raise ValueError(
            f"`cfg.modality` is 'mri' but {100 * air_hu:.0f} % of the voxels are below -500, as air in a CT "
            "(Hounsfield units); use SegmentConfig(modality='ct') for a CT."
        )
    if cfg.modality == "ct" and d.min() > -500:
        raise ValueError(
            f"`cfg.modality` is 'ct' but the lowest value is {d.min():.4g}: no air at about -1000 HU. "
            "Pass the CT in Hounsfield units (rescale slope/intercept applied), or use modality='mri'."
        )
    if atlas is not None:
        if not isinstance(atlas, Atlas):
            raise ValueError(f"`atlas` must be an Atlas (or None for the default), got {type(atlas).__name__}.")
        if atlas.modality != cfg.modality:
            raise ValueError(
                f"`atlas` was built for {atlas.modality!r} but `cfg.modality` is {cfg.modality!r}; pass an "
                f"atlas of the scan's modality (default_atlas({cfg.modality!r}))."
            )


def _em_data(volume: Volume, modality: str, denoise: bool = False):
    """MRI: log intensity with a floor at 1e-3 of the 99th percentile; CT: HU. With `denoise`, the
    intensities (MRI: the magnitude, before the log) are first smoothed by `denoise.diffuse` with an
    edge threshold of EDGE_FACTOR times their estimated noise sd (CT: `denoise.noise_sd`; MRI: the
    Rician channel sd from the air, `denoise.rayleigh_noise_sd`, else `noise_sd` with a warning)."""
    return _em_data_noise(volume, modality, denoise)[0]


def _noise_floor(sd: float | None) -> NoiseFloor | None:
    """The EM's NoiseFloor of an MRI (log intensity) with Rician channel noise sd `sd` (intensity
    units): the acquisition's log-Rician noise, `denoise.log_noise_table(., 0)` shifted by log sd,
    whether the scan was smoothed or not (see DEFAULT_NOISE_FLOOR). None without a measured noise
    (no air: a warning)."""
    if sd is None or not sd > 0:
        log.warning("segment (mri): no Rician noise measured from the air (denoise.rayleigh_noise_sd); the EM "
                    "runs without its noise floor")
        return None
    m, d = log_noise_table(EDGE_FACTOR, 0)
    return NoiseFloor(means=jnp.asarray(np.log(sd) + m), sds=jnp.asarray(d))


def _em_data_noise(volume: Volume, modality: str, denoise: bool = False, rician: bool = False):
    """`_em_data` and the noise sd it measured (intensity units; None if none): with `rician` (MRI),
    the Rayleigh estimate from the air even without `denoise` (None where there is no air)."""
    d = volume.data
    sd = None
    if modality == "mri" and (rician or denoise):
        sd = rayleigh_noise_sd(d)
    rician_sd = sd
    if denoise:
        sd = sd if modality == "mri" else noise_sd(d)
        if sd is None:
            log.warning("segment (mri): too little air around the head to measure the Rician noise from it "
                        "(denoise.rayleigh_noise_sd); the edge threshold uses the neighbour-difference estimate "
                        "instead (denoise.noise_sd: brain folding counts as noise, Rician air deflates it)")
            sd = noise_sd(d)
        log.info("segment (%s): noise sd %.4g (intensity units), edge-preserving smoothing k = %.4g",
                 modality, sd, EDGE_FACTOR * sd)
        if sd > 0:
            d = np.asarray(diffuse(jnp.asarray(d, jnp.float32), EDGE_FACTOR * sd, DENOISE_STEPS), dtype=np.float64)
    if modality == "ct":
        return d, sd
    p99 = np.percentile(d, 99)
    if p99 <= 0:
        raise ValueError("`volume` (MRI) has no positive intensities; pass a magnitude image.")
    return np.log(np.maximum(d, 1e-3 * p99)), rician_sd


def _scan_em_data(volume: Volume, cfg: SegmentConfig):
    """`_em_data_noise` as `cfg` says (denoised or not; the Rician sd from the air where the noise floor is on):
    the EM's data on the full grid, as a read-only view, and the noise sd. Computed once per segmentation and
    handed on in the fit (`_classify`'s sample, 5th item): ~0.1 s a call on a 1 mm head, six calls per MRI."""
    denoise = DEFAULT_DENOISE[cfg.modality] if cfg.denoise is None else cfg.denoise
    floor_on = DEFAULT_NOISE_FLOOR[cfg.modality] if cfg.noise_floor is None else cfg.noise_floor
    y, sd = _em_data_noise(volume, cfg.modality, denoise, rician=floor_on)
    y = np.asarray(y).view()
    y.setflags(write=False)  # shared by the steps of a segmentation (a view: a CT's array itself stays writable)
    return y, sd


def _dtype(cfg: SegmentConfig):
    dtype = jnp.float32 if cfg.precision == "float32" else jnp.float64
    if dtype == jnp.float64 and not jax.config.jax_enable_x64:
        raise ValueError("`cfg.precision` is 'float64' but JAX x64 is off; enable jax_enable_x64 at your entry point.")
    return dtype


#: Plausible affine registrations of a head scan to a head atlas (scan mm -> atlas mm): the singular
#: values of the linear part (head sizes of adults and children against the MNI152 head, which is
#: ~10-15 % larger per axis than an average brain), rotation (a scan tilted by more than this is not
#: a head scan positioned for imaging) and the NMI after the affine stage, measured at 4 mm with 32 bins
#: (`registration_summary`); see tests/test_segment_real.py and experiments/segmentation_accuracy.py
#: for the values on good and on mis-oriented scans.
MIN_SCALE, MAX_SCALE = 0.7, 1.4
MAX_ROTATION_DEG = 45.0
MIN_NMI = 1.06
#: NMI by which another axis orientation must beat the scan's own (`check_orientation`).
ORIENTATION_MARGIN = 0.01
#: The left-right mirror (RAS world x -> -x), which `check_orientation` does not judge.
LEFT_RIGHT_MIRROR = np.diag([-1.0, 1.0, 1.0])


def registration_summary(volume: Volume, atlas: Atlas, transform: Transform) -> dict:
    """Plausibility figures of an atlas registration (its affine part).

    Arguments:
        volume: the scan.
        atlas: the atlas registered to it.
        transform: scan mm -> atlas mm (AffineTransform or BSplineTransform).
    Returns:
        dict: scales (3 singular values of the linear part, descending), det, rotation_deg (angle of
        the rotation in its polar decomposition), nmi (normalised mutual information of scan and
        affinely warped template on a 4 mm grid, 32 bins; 1 = independent, 2 = identical).
    """
    m = np.asarray(transform.affine if isinstance(transform, BSplineTransform) else transform.matrix, np.float64)
    lin = m[:3, :3]
    u, sv, vt = np.linalg.svd(lin)
    det = float(np.linalg.det(lin))
    rot = u @ vt
    if np.linalg.det(rot) < 0:  # a reflection: report the rotation part of -R
        rot = -rot
    angle = float(np.degrees(np.arccos(np.clip((np.trace(rot) - 1) / 2, -1.0, 1.0))))
    factors = _level_factors(volume.affine, 4.0)
    fd, fa = downsample(volume.data, volume.affine, factors)
    warped = np.asarray(resample(atlas.template, atlas.affine, AffineTransform(matrix=jnp.asarray(m)), fd.shape, fa,
                                 dtype=jnp.float32))
    lo_f, hi_f = np.percentile(fd, [0.5, 99.5])
    lo_m, hi_m = np.percentile(warped, [0.5, 99.5])
    val = float(nmi(jnp.asarray(fd.ravel(), jnp.float32), jnp.asarray(warped.ravel(), jnp.float32),
                    (float(lo_f), float(max(hi_f, lo_f + 1e-6))), (float(lo_m), float(max(hi_m, lo_m + 1e-6))), 32))
    return dict(scales=[float(x) for x in sv], det=det, rotation_deg=angle, nmi=val)


def _signed_permutations() -> list[np.ndarray]:
    """The 48 axis permutations with signs (rotations by multiples of 90 deg, and their mirrors)."""
    out = []
    for perm in itertools.permutations(range(3)):
        for signs in itertools.product((1.0, -1.0), repeat=3):
            m = np.zeros((3, 3))
            m[np.arange(3), perm] = signs
            out.append(m)
    return out


def orientation_scores(volume: Volume, atlas: Atlas, resolution_mm: float = 8.0) -> list[tuple[np.ndarray, float]]:
    """NMI of the scan against the atlas template turned into each of the 48 axis orientations.

    The template is centred on the scan's intensity centre of mass and turned by each signed axis
    permutation P (scan mm -> atlas mm: q = c_atlas + P (p - c_scan)), without any optimisation, on a
    `resolution_mm` grid. A correctly oriented scan scores best (or ties with its left-right mirror,
    a head being nearly symmetric) at P = identity.

    Returns:
        list of (P (3, 3), NMI), identity first.
    """
    fd, fa = downsample(volume.data, volume.affine, _level_factors(volume.affine, resolution_mm))
    md, ma = downsample(atlas.template, atlas.affine, _level_factors(atlas.affine, resolution_mm))
    c_f, c_m = centre_of_mass(fd, fa), centre_of_mass(md, ma)
    lo_f, hi_f = np.percentile(fd, [0.5, 99.5])
    lo_m, hi_m = np.percentile(md, [0.5, 99.5])
    a = jnp.asarray(fd.ravel(), jnp.float32)
    out = []
    for p in _signed_permutations():
        m = np.eye(4)
        m[:3, :3] = p
        m[:3, 3] = c_m - p @ c_f
        w = resample(md, ma, AffineTransform(matrix=jnp.asarray(m, jnp.float32)), fd.shape, fa, dtype=jnp.float32)
        val = nmi(a, w.ravel(), (float(lo_f), float(max(hi_f, lo_f + 1e-6))),
                  (float(lo_m), float(max(hi_m, lo_m + 1e-6))), 32)
        out.append((p, float(val)))
    return out


def check_orientation(volume: Volume, atlas: Atlas, margin: float = ORIENTATION_MARGIN) -> dict:
    """Raise a ValueError when another axis orientation of the scan matches the atlas clearly better.

    The left-right mirror is not judged (a head is nearly symmetric: it ties with the scan's own
    orientation); a left-right swap in the header cannot be detected from the image.

    Arguments:
        volume: the scan.
        atlas: the atlas.
        margin: NMI by which the best other orientation must beat the scan's own to count as a
            mis-orientation (ORIENTATION_MARGIN, measured on good and turned scans).
    Returns:
        dict (nmi_as_given, nmi_best_other, best_other: the permutation as a nested list).
    """
    scores = orientation_scores(volume, atlas)
    own = scores[0][1]
    # A head is nearly mirror-symmetric left to right, so its left-right mirror matches the atlas as
    # well as the scan itself, up to noise and asymmetries of a few 0.01 NMI (phantom MRI seed 2 at
    # 2 mm: 1.166 vs 1.154): not evidence of a mis-orientation, and a left-right swap cannot be seen
    # this way at all. It is not judged; every other orientation is.
    others = [(p, v) for p, v in scores[1:] if not np.array_equal(p, LEFT_RIGHT_MIRROR)]
    p_best, best = max(others, key=lambda s: s[1])
    info = dict(nmi_as_given=own, nmi_best_other=best, best_other=p_best.tolist())
    if best > own + margin:
        names = "xyz"
        desc = ", ".join(f"scan {('-' if p_best[i, j] < 0 else '+')}{names[j]} -> atlas {names[i]}"
                         for i in range(3) for j in range(3) if p_best[i, j] != 0)
        codes = "".join(nib_axcodes(volume.affine))
        raise ValueError(
            f"`volume` looks mis-oriented: turned ({desc}) it matches the {atlas.name} atlas better (NMI "
            f"{best:.3f}) than as its affine places it ({own:.3f}). The affine says the voxel axes point "
            f"{codes} (RAS+ world). Check the header's sform/qform: open the scan in a viewer that uses it "
            "(e.g. fsleyes, or nilearn.plotting.plot_anat) and confirm the nose points to +y (anterior) "
            "and the top of the head to +z (superior); fix the header, or pass "
            "SegmentConfig(check_registration=False) if the scan really is positioned like this."
        )
    return info


def check_registration(summary: dict, volume: Volume) -> None:
    """Raise a ValueError when an atlas registration looks like a mis-oriented scan (see SegmentConfig)."""
    problems = []
    if summary["det"] < 0:
        problems.append("the best alignment mirrors the scan (left-right or another axis flipped)")
    sc = summary["scales"]
    if max(sc) > MAX_SCALE or min(sc) < MIN_SCALE:
        problems.append(f"it scales the head by {min(sc):.2f}..{max(sc):.2f} (plausible {MIN_SCALE}..{MAX_SCALE})")
    if summary["rotation_deg"] > MAX_ROTATION_DEG:
        problems.append(f"it rotates the head by {summary['rotation_deg']:.0f} deg (plausible <= {MAX_ROTATION_DEG:g})")
    if summary["nmi"] < MIN_NMI:
        problems.append(f"the aligned atlas matches the scan poorly (NMI {summary['nmi']:.3f} < {MIN_NMI})")
    if problems:
        codes = "".join(nib_axcodes(volume.affine))
        raise ValueError(
            "`volume` looks mis-oriented: the atlas registration ended implausibly: " + "; ".join(problems) + ". "
            f"Its affine says the voxel axes point {codes} (RAS+ world). Check the affine: open the scan in a "
            "viewer that uses it (e.g. fsleyes, or nilearn.plotting.plot_anat) and confirm the nose points "
            "to +y (anterior) and the top of the head to +z (superior); fix the header (e.g. nibabel "
            "as_closest_canonical does not fix a wrong header, reorient or correct the sform/qform) or pass "
            "SegmentConfig(check_registration=False) if the scan really is this unusual."
        )


def check_label_map(labels: LabelMap, volume: Volume, name: str = "labels") -> None:
    """Raise a ValueError unless a label map lies on the scan's grid (same shape and affine).

    A label map with another affine is another image's: comparing or combining it voxel by voxel with
    this scan would mix up anatomy.
    """
    if not isinstance(labels, LabelMap):
        raise ValueError(f"`{name}` must be a LabelMap, got {type(labels).__name__}.")
    if labels.shape != volume.shape:
        raise ValueError(
            f"`{name}` has shape {labels.shape} but the scan is {volume.shape}; resample the label map onto "
            "the scan's grid (nearest neighbour) or pass the label map made from this scan."
        )
    if not np.allclose(labels.affine, volume.affine, atol=1e-3):
        raise ValueError(
            f"`{name}` has a different affine from the scan's (max difference "
            f"{np.abs(labels.affine - volume.affine).max():.3g} mm):\n{np.round(labels.affine, 3)}\nvs\n"
            f"{np.round(volume.affine, 3)}.\nThe label map belongs to another grid or orientation; resample it "
            "onto the scan's grid (nearest neighbour), or fix whichever header is wrong."
        )


def dice_scores(labels: LabelMap, truth: LabelMap) -> dict[str, float]:
    """Dice overlap per tissue (brain, csf, skull, scalp) of two label maps on the same grid.

    Arguments:
        labels: e.g. `Segmentation.labels`.
        truth: the reference LabelMap (same shape and affine, else a ValueError).
    Returns:
        {tissue name: Dice in [0, 1]} (1 where neither map has the tissue).
    """
    check_label_map(truth, Volume(np.zeros(labels.shape), labels.affine), "truth")
    out = {}
    for t in Tissue:
        if t == Tissue.BACKGROUND:
            continue
        a, b = labels.labels == int(t), truth.labels == int(t)
        s = int(a.sum() + b.sum())
        out[t.name.lower()] = float(2 * (a & b).sum() / s) if s else 1.0
    return out


def register_atlas(volume: Volume, atlas: Atlas, cfg: SegmentConfig = SegmentConfig()):
    """Register the atlas template to the scan and resample the atlas priors onto the scan's grid.

    Arguments:
        volume: the scan.
        atlas: an Atlas of the scan's modality.
        cfg: SegmentConfig (its `register` settings and precision are used).
    Returns:
        (transform scan mm -> atlas mm, priors (5, x, y, z) jax array on the scan's grid).
    """
    dtype = _dtype(cfg)
    transform = register(volume, atlas.template_volume(), cfg.register, dtype=dtype)
    priors = resample(atlas.priors, atlas.affine, transform, volume.shape, volume.affine, dtype=dtype)
    return transform, priors


def unmodelled_on_grid(volume: Volume, atlas: Atlas, transform: Transform, cfg: SegmentConfig = SegmentConfig()):
    """The atlas's unmodelled-bone map (`Atlas.unmodelled`) on the scan's grid through the registration
    (scan mm -> atlas mm), in [0, 1]; None where the atlas has none. For `classify`."""
    if atlas.unmodelled is None:
        return None
    u = resample(atlas.unmodelled, atlas.affine, transform, volume.shape, volume.affine, dtype=_dtype(cfg))
    return np.clip(np.asarray(u), 0.0, 1.0)


def class_argmax(posteriors) -> np.ndarray:
    """`np.argmax(posteriors, axis=0)` (ties: the first class) by one pass per class: about twice as fast on a
    (5, x, y, z) float32 array at 1 mm, which `np.argmax` reduces along its slowest axis (it is called about a
    dozen times per MRI segmentation). Posteriors hold no NaN (np.argmax would return a NaN's index)."""
    p = np.asarray(posteriors)
    best = np.array(p[0], copy=True)
    idx = np.zeros(p.shape[1:], np.intp)
    for k in range(1, len(p)):
        above = p[k] > best
        np.maximum(best, p[k], out=best)
        idx[above] = k
    return idx


def classify(volume: Volume, priors, cfg: SegmentConfig = SegmentConfig(), unmodelled=None):
    """EM + MRF classification of a scan given priors on its grid (the second half of `segment`).

    Arguments:
        volume: the scan (MRI magnitude or CT in HU).
        priors: (5, x, y, z) class priors on the scan's grid (e.g. from `register_atlas`).
        cfg: SegmentConfig.
        unmodelled: optional (x, y, z) in [0, 1] on the scan's grid: where the atlas does not model
            bone (`Atlas.unmodelled`, resampled; its priors there are placeholder soft tissue). There
            the proportions of UNMODELLED_CLASSES (skull, scalp) are learnt from the scan: a first EM
            run with the atlas priors (there, by `cfg.unmodelled_start`, equal shares of those classes,
            the atlas's placeholder, or equal shares checked for a runaway), on the
            `cfg.first_pass_sample_mm` sample, fits the class intensity models; their likelihoods at
            each voxel of that region give the maximum-likelihood proportions
            (`atlas.regional_proportions`; voxel weight = unmodelled x the classes' share of the
            likelihood); a second run, from its own start (not where the first stopped), uses priors
            that share that region in those proportions (`atlas.with_proportions`).
    Returns:
        (posteriors (5, x, y, z) float32 numpy, EMResult of the parameter fit (on the strided
        sample), EMOptions used, bias coordinates of the full grid).
    """
    return _classify_all(volume, priors, cfg, unmodelled)[:4]


def checked_start(learn, n_classes: int, k: int) -> tuple[object, np.ndarray, dict]:
    """`unmodelled_start = "checked"`: equal shares, checked for a runaway (DEFAULT_UNMODELLED_START's comment).

    The share of class `k` learnt from equal shares runs away if it rose above its equal start and a second
    pass from it raises it further: the iteration share -> first EM -> share climbs away from its start towards
    its upper fixed point. Then the placeholder's fit (`learn(None)`) is used. No second pass where the first
    learnt no more than the equal share, so there the result and the cost are "equal"'s.

    Arguments:
        learn: shares (n_classes,) or None (the atlas's placeholder) -> (a fit, the shares it learnt).
        n_classes: the classes that share the region (len(UNMODELLED_CLASSES)).
        k: the index among them of the class whose share is checked (the skull).
    Returns:
        (the fit used, its learnt shares, figures for the run report: the share learnt from equal shares, from
        those again where it was run, whether it ran away, and, if it did, the share learnt from the placeholder).
    """
    fit, pi = learn(np.full(n_classes, 1.0 / n_classes))
    check = dict(equal=round(float(pi[k]), 4), runaway=False)
    if pi[k] > 1.0 / n_classes:
        _, again = learn(pi)
        check.update(again=round(float(again[k]), 4), runaway=bool(again[k] > pi[k]))
    if check["runaway"]:
        fit, pi = learn(None)
        check["atlas"] = round(float(pi[k]), 4)
    return fit, pi, check


def _first_pass(volume: Volume, priors, cfg: SegmentConfig, unmodelled, data=None, report: dict | None = None):
    """`classify`'s first EM where the atlas models no bone (`unmodelled`), on the `first_pass_sample_of()` sample,
    from equal skull/scalp shares there, the atlas's placeholder, or "checked" (`unmodelled_start_of()`;
    DEFAULT_UNMODELLED_START's comment; `checked_start`). Returns (its EMResult, the shares of UNMODELLED_CLASSES
    it learnt there). `data`: as `_classify`'s. `report`: a dict that gets "checked"'s figures (None: not kept)."""
    start = cfg.unmodelled_start_of()

    def learn(shares):
        first = priors if shares is None else with_proportions(np.asarray(priors), unmodelled, shares)
        _, res, _, _, pi, _ = _classify(volume, first, cfg, unmodelled, sample_mm=cfg.first_pass_sample_of(),
                                        data=data)
        return res, pi

    n = len(UNMODELLED_CLASSES)
    if start == "checked":
        res, pi, check = checked_start(learn, n, UNMODELLED_CLASSES.index(Tissue.SKULL))
        log.info("segment (%s): skull share where the atlas models no bone, checked: %s", cfg.modality, check)
        if report is not None:
            report.update(check)
    else:
        res, pi = learn(None if start == "atlas" else np.full(n, 1.0 / n))
    log.info("segment (%s): %s proportions learnt where the atlas models no bone: %s", cfg.modality,
             [Tissue(c).name.lower() for c in UNMODELLED_CLASSES], np.round(pi, 3).tolist())
    return res, pi


def _classify_all(volume: Volume, priors, cfg: SegmentConfig, unmodelled=None, report: dict | None = None):
    """`classify`, also returning the learnt unmodelled-region proportions (None without) and the EM's
    sample: its data, bias coordinates and grid affine (for `_refine_warp`), and the EM's data on the
    full grid (for the steps after the EM that judge intensities by its Gaussians). `report`: `_first_pass`'s."""
    if unmodelled is None:
        return _classify(volume, priors, cfg)
    data = _scan_em_data(volume, cfg)
    _, pi = _first_pass(volume, priors, cfg, unmodelled, data, report)
    # The second EM starts from its own start on the new priors, not from where the first stopped: the first
    # only has to learn `pi`, so it may sample more sparsely (`first_pass_sample_mm`). Warm-started, the second
    # EM inherited the first's end point: from the placeholder start its scalp class kept some of the region's
    # bone (CT 2 mm, ANTs head: skull 0.985 -> 0.973); from equal shares, with the first pass at 3 or 4 mm, a
    # met row was lost (experiments/results/segmentation_first_pass.md).
    post, res, opts, coords, _, sample = _classify(volume, with_proportions(np.asarray(priors), unmodelled, pi), cfg,
                                                   data=data)
    return post, res, opts, coords, pi, sample


def sample_stride(em_sample_mm: float, voxel_mm) -> tuple[int, ...]:
    """The EM sample's stride per axis (`SegmentConfig.em_sample_mm`): em_sample_mm / voxel rounded to the nearest
    whole number (Python's `round`: a tie goes to the even one), at least 1. With 2 mm: 2 at 1 mm and at 1.2 mm,
    1 at 1.5, 2 and 4 mm, 3 at 0.7 mm.

    Arguments:
        em_sample_mm: the sampling distance, mm (> 0).
        voxel_mm: the grid's voxel sizes (3,), mm.
    Returns:
        (3,) strides.
    """
    return tuple(max(1, int(round(em_sample_mm / float(v)))) for v in voxel_mm)


def _classify(volume: Volume, priors, cfg: SegmentConfig, unmodelled=None, init=None, sample_mm=None, data=None):
    """`classify` with one set of priors. With `unmodelled` (a first pass), the proportions of
    UNMODELLED_CLASSES in that region instead of the posteriors (None): `atlas.regional_proportions`
    of the class likelihoods at the fitted parameters (posteriors under a uniform prior, no MRF, no
    relaxation) on the EM's sample grid, voxel weight = unmodelled x the classes' share of the
    likelihood. The sample grid, not the full one: the proportions of a region of 10^5-10^6 voxels are
    as well determined from every k-th voxel, and at 1 mm the full grid costs seconds (profiled on
    the case of benchmarks/segment.py: 4.4 s of 17 s of `classify`). `init`: the EM's starting
    MixtureParams (a fit on other priors, for the steps that run it again); None: the atlas-weighted
    quantiles of the scan (`em.fit_mixture`). `sample_mm`: the EM's sampling distance (None: `cfg.em_sample_mm`).
    `data`: `_scan_em_data(volume, cfg)` if already computed (None: computed here); returned as the sample's
    5th item."""
    dtype = _dtype(cfg)
    vox = voxel_sizes(volume.affine)
    stride = sample_stride(cfg.em_sample_mm if sample_mm is None else sample_mm, vox)
    # Pad the grid (edge values: air) up to a multiple of 8 strided voxels so that scans of similar
    # size share compiled code; the padding is cropped off the results.
    shape = volume.shape
    padded = tuple(-(-n // (8 * s)) * 8 * s for n, s in zip(shape, stride))
    pad = [(0, p - n) for p, n in zip(padded, shape)]
    floor_on = DEFAULT_NOISE_FLOOR[cfg.modality] if cfg.noise_floor is None else cfg.noise_floor
    data = _scan_em_data(volume, cfg) if data is None else data
    y, sd = data
    y_full = jnp.asarray(np.pad(y, pad, mode="edge"), dtype)
    nfloor = _noise_floor(sd) if floor_on else None
    if nfloor is not None:
        nfloor = NoiseFloor(means=nfloor.means.astype(dtype), sds=nfloor.sds.astype(dtype))
    priors = jnp.pad(jnp.asarray(priors, dtype), [(0, 0)] + pad, mode="edge")
    sl = tuple(slice(None, None, s) for s in stride)
    opts = cfg.em_options(cfg.relax_sigma_mm / float(np.mean(vox * np.asarray(stride))))
    coords_full = _coords(shape, padded, 1, dtype)
    coords_s = tuple(c[::s] for c, s in zip(coords_full, stride))
    priors_s = priors[(slice(None),) + sl]
    res = fit_mixture(y_full[sl], priors_s, opts, init, coords_s, nfloor)
    log.info(
        "segment (%s): EM %d iterations (converged %s), means %s", cfg.modality, int(res.n_iter),
        bool(res.converged), np.round(np.asarray(res.params.means), 3).tolist(),
    )
    crop = (slice(None),) + tuple(slice(0, n) for n in shape)
    post = pi = None
    if unmodelled is not None:  # a first pass: only the proportions are used, so the MRF sweeps are skipped
        flat = replace(cfg.em_options(1.0), beta=0.0, relax=0.0)
        uniform = jnp.full_like(priors_s, 1.0 / N_CLASSES)
        k = [int(c) for c in UNMODELLED_CLASSES]
        lik = np.asarray(infer_posteriors(y_full[sl], uniform, res.params, flat, 0, coords_s)[np.asarray(k)])
        u = np.pad(np.asarray(unmodelled, np.float32), pad)[sl]  # the padding is outside the scan: weight 0
        pi = regional_proportions(lik, u * lik.sum(0))
    elif all(s == 1 for s in stride):
        post = np.asarray(res.posteriors[crop], dtype=np.float32)  # the EM ran on the full grid
    else:
        opts_full = cfg.em_options(cfg.relax_sigma_mm / float(np.mean(vox)))
        post = infer_posteriors(y_full, priors, res.params, opts_full, cfg.sweeps, coords_full)
        post = np.asarray(post[crop], dtype=np.float32)
    sample_affine = np.asarray(volume.affine, np.float64) @ np.diag([*stride, 1.0])
    sample = (y_full[sl], coords_s, sample_affine, y_full[crop[1:]], data)
    return post, res, opts, tuple(c[:n] for c, n in zip(coords_full, shape)), pi, sample


def segment_reported(volume: Volume, atlas: Atlas | None = None,
                     cfg: SegmentConfig = SegmentConfig()) -> tuple[LabelMap, Segmentation]:
    """Segment a head MRI or CT into BACKGROUND, BRAIN, CSF, SKULL and SCALP, with the fitted model.

    Arguments:
        volume: the scan (MRI: magnitude, arbitrary units; CT: Hounsfield units).
        atlas: an Atlas of the same modality; None uses `default_atlas(cfg.modality)` (cached).
        cfg: SegmentConfig.
    Returns:
        (labels, report): the LabelMap of Tissue values on the scan's grid, and a Segmentation
        (posteriors, transform, mixture parameters, bias field, EM iterations, atlas, registration
        figures).
    """
    _check_inputs(volume, atlas, cfg)
    _dtype(cfg)
    padding = {}
    if cfg.modality == "ct":
        volume, padding = replace_ct_padding(volume)
        if padding:
            log.info("segment (ct): %d padding voxels (below %g HU, lowest %g) set to the air's %g HU",
                     padding["voxels"], CT_PADDING_BELOW_HU, padding["lowest_hu"], padding["air_hu"])
    if atlas is None:
        atlas = config_atlas(cfg)
    t0 = time.perf_counter()
    orientation = check_orientation(volume, atlas) if cfg.check_registration else {}
    transform, priors = register_atlas(volume, atlas, cfg)
    priors.block_until_ready()
    unmodelled = unmodelled_on_grid(volume, atlas, transform, cfg)
    summary = {**registration_summary(volume, atlas, transform), **orientation}
    if padding:
        summary["ct_padding"] = padding
    log.info("registration to the %s atlas: scales %s, rotation %.1f deg, det %.3f, NMI %.4f", atlas.name,
             np.round(summary["scales"], 3).tolist(), summary["rotation_deg"], summary["det"], summary["nmi"])
    if cfg.check_registration:
        check_registration(summary, volume)
    t1 = time.perf_counter()
    first_pass = {}
    post, res, opts, coords, pi, sample = _classify_all(volume, priors, cfg, unmodelled, first_pass)
    if cfg.refine_rounds() > 0:
        transform, (post, res, opts, coords, pi, sample), summary["warp_refinement"] = _refine_warp(
            volume, atlas, transform, (post, res, opts, coords, pi, sample), cfg)
    if pi is not None:  # the shares the later steps use (re-learnt by the warp refinement where it ran)
        summary["unmodelled"] = {"start": cfg.unmodelled_start_of(), **{
            Tissue(c).name.lower(): round(float(p), 4) for c, p in zip(UNMODELLED_CLASSES, pi)}}
        if first_pass:  # "checked": the first pass's skull shares (before any warp refinement)
            summary["unmodelled"]["checked"] = first_pass
    if cfg.depth_prior_on():
        if cfg.refine_rounds() > 0:  # the priors (and unmodelled map) of the refined warp
            priors = resample(atlas.priors, atlas.affine, transform, volume.shape, volume.affine, dtype=_dtype(cfg))
            unmodelled = unmodelled_on_grid(volume, atlas, transform, cfg)
        (post, res, opts, coords, pi, sample), summary["depth_prior"] = _depth_prior(
            volume, atlas, np.asarray(priors), unmodelled, pi, post, cfg)
    if (cfg.layer_split_on() or cfg.marrow_inside_skull_on()) and cfg.refine_rounds() > 0 and not cfg.depth_prior_on():
        priors = resample(atlas.priors, atlas.affine, transform, volume.shape, volume.affine, dtype=_dtype(cfg))
        unmodelled = unmodelled_on_grid(volume, atlas, transform, cfg)
    if cfg.marrow_inside_skull_on():
        priors, (post, res, opts, coords, pi, sample), summary["marrow_inside_skull"], given_back = \
            _marrow_inside_skull(volume, np.asarray(priors), unmodelled, pi, (post, res, opts, coords, pi, sample),
                                 cfg, defer_mirror=cfg.layer_split_on())
    else:
        given_back = None
    if cfg.csf_inside_tables_on():
        priors = np.array(priors, np.float32, copy=True)
        (post, res, opts, coords, pi, sample), inside = _csf_inside_tables(
            volume, priors, unmodelled, pi, (post, res, opts, coords, pi, sample), cfg)
        summary["csf_inside_tables"] = {"before_layer_split": inside}
    if cfg.layer_split_on():
        # the split's priors are kept only for csf_inside_tables (5 x the grid in float32: 140 MB at 1 mm)
        split = _layer_split(volume, np.asarray(priors), unmodelled, pi, (post, res, opts, coords, pi, sample), cfg,
                             return_priors=cfg.csf_inside_tables_on(), given_back=given_back)
        (post, res, opts, coords, pi, sample), summary["layer_split"] = split[:2]
        if cfg.csf_inside_tables_on():  # the split shares CSF + skull afresh by depth: look again after it
            (post, res, opts, coords, _, sample), inside = _csf_inside_tables(
                volume, split[2], None, None, (post, res, opts, coords, pi, sample), cfg)
            summary["csf_inside_tables"]["after_layer_split"] = inside
    if cfg.marrow_tables_on():
        post, summary["marrow_tables"] = _marrow_tables(volume, (post, res, opts, coords, pi, sample), cfg)
    if cfg.modality == "ct" and cfg.bone_majority:
        post, info = bone_majority(np.asarray(volume.data), post)
        summary["bone_majority"] = {k: round(v, 1) for k, v in info.items()}
        log.info("segment (ct): bone majority rule %s", summary["bone_majority"])
    if cfg.modality == "ct" and cfg.air_majority:
        post, info = air_majority(np.asarray(volume.data), post)
        summary["air_majority"] = {k: round(v, 1) for k, v in info.items()}
        log.info("segment (ct): air majority rule %s", summary["air_majority"])
    if cfg.modality == "ct" and cfg.scalp_outside_skull:
        y = np.asarray(sample[3], np.float64)  # the EM's data on the full grid: its Gaussians describe these
        if opts.bias_degree > 0:
            y = y - np.asarray(bias_field(res.params.bias, coords, opts.bias_degree), dtype=np.float64)
        post, summary["scalp_outside_skull"] = scalp_outside_skull(post, y, res.params, opts)
        log.info("segment (ct): scalp enclosed by the skull beside brain or CSF relabelled: %s",
                 summary["scalp_outside_skull"])
    t2 = time.perf_counter()
    log.info("segment timings (s, compile included): registration %.1f, EM + MRF %.1f", t1 - t0, t2 - t1)
    labels = LabelMap(class_argmax(post).astype(np.uint8), volume.affine)
    if opts.bias_degree > 0:
        b = np.asarray(bias_field(res.params.bias, coords, opts.bias_degree), dtype=np.float64)
        bias = np.exp(b) if cfg.modality == "mri" else b
    else:
        bias = np.ones(volume.shape) if cfg.modality == "mri" else np.zeros(volume.shape)
    params = jax.tree.map(np.asarray, res.params)
    return labels, Segmentation(
        labels=labels, posteriors=post, transform=transform, params=params, component_class=opts.component_class,
        bias_field=bias, n_iter=int(res.n_iter), converged=bool(res.converged), atlas_name=atlas.name,
        registration=summary,
    )


def _refine_warp(volume: Volume, atlas: Atlas, transform: BSplineTransform, fit, cfg: SegmentConfig):
    """Alternate warp refinement on the EM's likelihood and the EM (`warp_refine.alternate`), at most
    `cfg.refine_rounds()` times. `fit` is `_classify_all`'s output. The priors of the warp objective are
    the atlas's with the learnt unmodelled-region proportions applied on the atlas grid (where the EM
    applies them after resampling: the two differ only within the trilinear interpolation).
    Returns (transform, fit, summary for the run report)."""
    t0 = time.perf_counter()
    anchor = transform.coefficients  # every round's change penalty is measured from the registration
    scale = cfg.warp_change_scale()

    def make_problem(tr, fit):
        _, res, opts, _, pi, sample = fit
        y_s, coords_s, sample_affine = sample[:3]
        priors = atlas.priors if pi is None else with_proportions(atlas.priors, atlas.unmodelled, pi)
        return warp_problem(y_s, coords_s, res.params, res.posteriors, opts, priors, atlas.affine, tr,
                            sample_affine, cfg.register.bending_energy, stride, anchor, scale)

    def refit(tr):
        priors = resample(atlas.priors, atlas.affine, tr, volume.shape, volume.affine, dtype=_dtype(cfg))
        return _classify_all(volume, priors, cfg, unmodelled_on_grid(volume, atlas, tr, cfg))

    sample_vox = float(np.mean(voxel_sizes(fit[5][2])))
    stride = max(1, round(WARP_SAMPLE_MM / sample_vox))
    step = stride * sample_vox  # the solver's first step: about a voxel of the objective's grid
    transform, fit, summary = alternate(transform, fit, make_problem, refit, cfg.refine_rounds(), cfg.register,
                                        step, cfg.tol)
    summary["change_scale_mm"] = scale
    summary["seconds"] = round(time.perf_counter() - t0, 1)
    log.info("segment (%s): warp refined on the EM likelihood: %s", cfg.modality, summary)
    return transform, fit, summary


def _depth_prior(volume: Volume, atlas: Atlas, priors: np.ndarray, unmodelled, pi, post, cfg: SegmentConfig):
    """The EM again on priors whose CSF/skull split follows the atlas's p(CSF | depth) at the depth
    between the brain and scalp of `post` (`depth_prior.with_depth_profile`), after the learnt
    proportions `pi` (None: none) where the atlas models no bone. Returns (`_classify_all`'s output,
    summary for the run report)."""
    t0 = time.perf_counter()
    profile, _ = csf_depth_profile(np.asarray(atlas.priors), voxel_sizes(atlas.affine))
    labels = class_argmax(post)
    _brain_and_scalp(labels, "depth_prior")
    if pi is not None:  # the proportions learnt where the atlas models no bone are kept, not re-learnt
        priors = with_proportions(priors, unmodelled, pi)
    fit = _classify(volume, with_depth_profile(priors, labels, voxel_sizes(volume.affine), profile), cfg)
    fit = fit[:4] + (pi,) + fit[5:]
    changed = class_argmax(fit[0]) != labels
    summary = dict(profile=np.round(profile, 3).tolist(), relabelled_fraction=round(float(changed.mean()), 4),
                   seconds=round(time.perf_counter() - t0, 1))
    log.info("segment (%s): CSF/skull priors by depth between brain and scalp: %s", cfg.modality, summary)
    return fit, summary


def _brain_and_scalp(labels: np.ndarray, step: str) -> None:
    missing = [t.name.lower() for t in (Tissue.BRAIN, Tissue.SCALP) if not (labels == t).any()]
    if missing:
        raise ValueError(
            f"[segment] {step}: the first EM labelled no {' and no '.join(missing)} voxel, so there is no "
            "depth between brain and scalp; the scan may not be a head MRI (check `modality` and the scan), or "
            f"set {step} = false.")


def _coarser_than_a_table(volume: Volume, why: str) -> str | None:
    """The run report's reason a step that follows the skull's compact tables is skipped (`why` says what it cannot
    do), where the scan's coarsest voxel side is above MARROW_MAX_VOXEL_MM; None where it runs."""
    vox = float(np.max(voxel_sizes(volume.affine)))
    if vox <= MARROW_MAX_VOXEL_MM:
        return None
    return f"voxels of {vox:.3g} mm, coarser than a compact table ({MARROW_MAX_VOXEL_MM} mm, MARROW_MAX_VOXEL_MM): {why}"


def _marrow_inside_skull(volume: Volume, priors: np.ndarray, unmodelled, pi, fit, cfg: SegmentConfig,
                         defer_mirror: bool = False):
    """Scalp-labelled voxels that the segmented skull encloses (`marrow_enclosed`) get their
    scalp prior moved to skull, and the EM runs again from the last fit; repeated while the newly enclosed
    voxels are at least MARROW_MIN_SHARE of the skull-labelled ones, at most MARROW_ROUNDS times
    (DEFAULT_MARROW_INSIDE_SKULL's comment). Then the mirror: once the skull class has a fat-bright Gaussian
    (`tables_cut`), skull-labelled voxels as bright as it that the tables do not enclose
    (`bright_skull_outside_tables`: scalp fat, not marrow) get their skull prior moved to scalp and the EM runs
    again from its own start, if they are at least MARROW_MIN_SHARE of the skull-labelled voxels. `fit` is
    `_classify_all`'s output, `pi` the proportions learnt where the atlas models no bone (None: none), kept.
    With `defer_mirror` (the layer split runs next) the mirror's priors are moved but its EM is not run: the
    layer split's EM, from its own start, is that EM too (`_layer_split`'s `given_back`); one EM run fewer, the
    split learnt on labels with those voxels given to the scalp. Session 28: benchmarks/segment.py 29.2-30.0 s ->
    24.5 s; on the adult-marrow 1 mm table the rows meeting the bars stay 4 of 6, the ANTs head's CSF moves by
    -0.004 to -0.032 (experiments/results/segmentation_mirror_deferred_fatty_mri_1mm.md).
    Returns (the priors, without those proportions applied, for the later steps; the fit; summary for the run
    report; the voxels given back whose EM was deferred, or None)."""
    t0 = time.perf_counter()
    vox = float(np.max(voxel_sizes(volume.affine)))
    if skipped := _coarser_than_a_table(volume, "the tables cannot enclose the marrow"):
        summary = dict(rounds=0, voxels=0, skipped=skipped)
        log.info("segment (%s): marrow_inside_skull skipped: %s", cfg.modality, skipped)
        return priors, fit, summary, None
    priors = np.array(priors, np.float32, copy=True)
    moved, total, below = [], np.zeros(priors.shape[1:], bool), 0
    for _ in range(MARROW_ROUNDS):
        labels = class_argmax(fit[0])
        skull = labels == Tissue.SKULL
        if not (skull.any() and ((labels == Tissue.SCALP) & ~total).any()):  # no skull, or no scalp left to give
            break
        dark = _table_dark(labels, corrected_em_data(volume, fit, cfg), table_dark_cut(fit))
        inside = marrow_enclosed(labels, dark, vox) & ~total
        if inside.sum() < MARROW_MIN_SHARE * skull.sum():  # none, or speckle
            below = int(inside.sum())
            break
        moved.append(int(inside.sum()))
        total |= inside
        fit = _refit_with_prior_moved(volume, priors, inside, Tissue.SCALP, Tissue.SKULL, unmodelled, pi, fit, cfg)
    given_back, cut, deferred = 0, tables_cut(fit), None
    if cut is not None:  # the skull class has learnt a marrow's fat: scalp fat beside the outer table may have too
        labels = class_argmax(fit[0])
        out = bright_skull_outside_tables(labels, corrected_em_data(volume, fit, cfg), cut)
        if out.sum() >= MARROW_MIN_SHARE * (labels == Tissue.SKULL).sum():
            given_back = int(out.sum())
            if defer_mirror:
                priors[Tissue.SCALP][out] += priors[Tissue.SKULL][out]
                priors[Tissue.SKULL][out] = 0.0
                deferred = out
            else:
                # from the EM's own start: the skull's fat-bright Gaussian may have described only this fat, and
                # started from it, it drifts to the brightest voxels the skull's prior still reaches (white matter)
                fit = _refit_with_prior_moved(volume, priors, out, Tissue.SKULL, Tissue.SCALP, unmodelled, pi, fit,
                                              cfg, fresh=True)
    summary = dict(rounds=len(moved), voxels_per_round=moved, voxels=int(total.sum()), left_below_share=below,
                   min_share=MARROW_MIN_SHARE, given_back_to_scalp=given_back,
                   given_back_em="deferred to the layer split" if deferred is not None else
                   ("run" if given_back else "none"), seconds=round(time.perf_counter() - t0, 1))
    log.info("segment (%s): scalp enclosed by the skull given to the skull: %s", cfg.modality, summary)
    return priors, fit, summary, deferred


def _refit_with_prior_moved(volume: Volume, priors: np.ndarray, mask, src: Tissue, dst: Tissue, unmodelled, pi, fit,
                            cfg: SegmentConfig, fresh: bool = False):
    """Move class `src`'s prior to class `dst` at `mask` (in place in `priors`, float32) and run the EM again from
    `fit`'s parameters (`fresh`: from the EM's own start on the new priors), the learnt proportions `pi` (None:
    none) kept. Returns `_classify_all`'s output."""
    priors[dst][mask] += priors[src][mask]
    priors[src][mask] = 0.0
    first = with_proportions(priors, unmodelled, pi) if pi is not None else priors
    new = _classify(volume, first, cfg, init=None if fresh else fit[1].params, data=_fit_data(fit))
    return new[:4] + (pi,) + new[5:]


def enclosed_background(labels: np.ndarray) -> np.ndarray:
    """Background voxels that tissue encloses (every one of the 26 grid rays meets a non-background voxel before
    the grid's edge, `enclosed`): bone as dark as air, say, not air a ray can leave the head through."""
    bg = np.asarray(labels) == Tissue.BACKGROUND
    return bg & enclosed(~bg, np.zeros_like(bg))


def _fit_data(fit):
    """The EM data a fit was computed on (`_classify`'s sample, 5th item; `_scan_em_data`), None where `fit` is
    (posteriors, EMResult, EMOptions, coords) without its sample."""
    return fit[5][4] if len(fit) > 5 else None


def corrected_em_data(volume: Volume, fit, cfg: SegmentConfig) -> np.ndarray:
    """The EM's data of `volume` (`_em_data_noise`, denoised as `cfg` says) less the bias field of `fit`
    ((posteriors, EMResult, EMOptions, coords, ...)), float64: what the fitted Gaussian means describe. Without a
    bias field it is the fit's shared EM data itself (read-only)."""
    _, res, opts, coords = fit[:4]
    data = _fit_data(fit)
    y = (_scan_em_data(volume, cfg) if data is None else data)[0]
    if opts.bias_degree > 0:
        y = y - np.asarray(bias_field(res.params.bias, coords, opts.bias_degree), dtype=np.float64)
    return y


def marrow_enclosed(labels: np.ndarray, dark: np.ndarray | None = None, voxel_mm: float = 1.0) -> np.ndarray:
    """Scalp-labelled voxels that the segmented skull encloses (`marrow_inside_skull`): every one of the 26
    grid rays (`enclosed`) meets skull, or background that tissue encloses, before background that a ray can
    leave the grid through. Background that tissue encloses is bone as dark as air (a compact table labelled
    background): a way out for no ray, so it walls the marrow as the skull does. So do scalp-labelled voxels
    as dark as compact bone (`dark`, `_table_dark`) farther than SKIN_LAYER_MM from that way out (through dark
    voxels): an outer table the scalp class took with its dark Gaussian (the one it keeps for the skin's partial
    volume with air, the dark layer that touches the air). Such walls are not marrow.

    Arguments:
        labels: (x, y, z) Tissue labels.
        dark: optional (x, y, z) boolean: voxels as dark as compact bone (None: none).
        voxel_mm: the grid's coarsest voxel side (mm), for SKIN_LAYER_MM.
    Returns:
        (x, y, z) boolean.
    """
    labels = np.asarray(labels)
    return _marrow_enclosed(labels, enclosed_background(labels), dark, voxel_mm)


def _marrow_enclosed(labels: np.ndarray, held: np.ndarray, dark: np.ndarray | None = None,
                     voxel_mm: float = 1.0) -> np.ndarray:
    """`marrow_enclosed` with the background that tissue encloses (`enclosed_background(labels)`) given."""
    scalp, escape = labels == Tissue.SCALP, (labels == Tissue.BACKGROUND) & ~held
    wall = (labels == Tissue.SKULL) | held
    if dark is not None and (dark := np.asarray(dark, bool) & scalp).any():
        wall = wall | (dark & ~_skin_layer(dark, escape, voxel_mm))
    return scalp & ~wall & enclosed(wall, escape)


def _skin_layer(dark: np.ndarray, escape: np.ndarray, voxel_mm: float) -> np.ndarray:
    """The voxels of `dark` within SKIN_LAYER_MM of `escape` through `dark` (geodesic, 26-neighbourhood steps of
    the coarsest voxel side `voxel_mm`, at least one step)."""
    cube = np.ones((3, 3, 3), bool)
    reach = ndimage.binary_dilation(escape, cube) & dark
    for _ in range(max(1, int(np.ceil(SKIN_LAYER_MM / voxel_mm))) - 1):
        reach = ndimage.binary_dilation(reach, cube) & dark
    return reach


def table_dark_cut(fit) -> float | None:
    """The upper end of compact bone's intensity in `fit` ((posteriors, EMResult, EMOptions, ...)), EM data units:
    the mean + 2 sd of the skull class's darkest live Gaussian (`_live_means`' share), which describes the tables
    (compact bone is dark in every MR contrast). None without a live skull Gaussian."""
    _, res, opts = fit[:3]
    means, var, w = (np.asarray(a, np.float64) for a in (res.params.means, res.params.variances, res.params.weights))
    live = (w >= MARROW_MIN_SHARE) & (np.asarray(opts.component_class) == int(Tissue.SKULL))
    if not live.any():
        return None
    j = np.flatnonzero(live)[np.argmin(means[live])]
    return float(means[j] + 2.0 * np.sqrt(var[j]))


def _table_dark(labels: np.ndarray, y, cut: float | None) -> np.ndarray | None:
    """Scalp-labelled voxels of `labels` darker than `cut` (`table_dark_cut`; None: None)."""
    return None if cut is None else (np.asarray(labels) == Tissue.SCALP) & (np.asarray(y) < cut)


def _csf_inside_tables(volume: Volume, priors: np.ndarray, unmodelled, pi, fit, cfg: SegmentConfig):
    """`csf_inside_tables` once: skull-labelled voxels of `fit` that `bright_skull_inside_tables` finds (cut:
    `csf_inside_cut`) get their skull prior moved to CSF (in place in `priors`, float32) and the EM runs again from
    `fit`'s parameters, if they are at least MARROW_MIN_SHARE of the skull-labelled voxels. `unmodelled`, `pi`:
    the learnt proportions to apply to `priors` (None: applied already, or none). Returns (`_classify_all`'s
    output, or `fit` unchanged; summary for the run report)."""
    if skipped := _coarser_than_a_table(volume, "no table to find CSF inside"):
        return fit, dict(voxels=0, skipped=skipped)
    means = {f"{c.name.lower()}_means": np.round(_live_means(fit, c), 4).tolist()
             for c in (Tissue.BRAIN, Tissue.CSF, Tissue.SKULL)}
    if skull_cut(fit) is None:
        return fit, dict(voxels=0, skipped="the skull class has fewer than two Gaussians with weight", **means)
    if (cut := csf_inside_cut(fit)) is None:
        return fit, dict(voxels=0, skipped="the skull class learnt a Gaussian brighter than the brain's darkest: "
                         "a fat-bright marrow (marrow_inside_skull's case), not CSF", **means)
    labels = class_argmax(fit[0])
    out = bright_skull_inside_tables(labels, corrected_em_data(volume, fit, cfg), cut)
    n, n_skull = int(out.sum()), int((labels == Tissue.SKULL).sum())
    summary = dict(cut=round(cut, 4), found=n, skull_voxels=n_skull, min_share=MARROW_MIN_SHARE, voxels=0, **means)
    if n >= MARROW_MIN_SHARE * n_skull and n > 0:
        fit = _refit_with_prior_moved(volume, priors, out, Tissue.SKULL, Tissue.CSF, unmodelled, pi, fit, cfg)
        summary["voxels"] = n
    log.info("segment (%s): bright skull inside the tables given to CSF: %s", cfg.modality, summary)
    return fit, summary


def skull_cut(fit) -> float | None:
    """The midpoint of the skull class's darkest and brightest Gaussian means of `fit` ((posteriors, EMResult,
    EMOptions, ...)), in the EM's data units: between the compact tables and whatever else the skull class
    describes (a marrow, or tissue it took). None with fewer than two Gaussians of at least MARROW_MIN_SHARE of
    the class's weight."""
    skull = _live_means(fit, Tissue.SKULL)
    return None if skull.size < 2 else 0.5 * float(skull.min() + skull.max())


def csf_inside_cut(fit) -> float | None:
    """`skull_cut` of `fit` ((posteriors, EMResult, EMOptions, ...)) where the skull class's Gaussians are all
    darker than the brain class's darkest, else None. On T1, CSF is darker than grey matter and a child's red
    marrow is as dark as CSF, so a skull class with every Gaussian below the brain can have learnt CSF's
    intensity (`csf_inside_tables`' case). A skull Gaussian brighter than the brain's darkest is an adult's
    fat-bright marrow (`tables_cut`, `marrow_inside_skull`'s case): on the MNI152 head's adult-marrow 8 % scan of
    random contrast 2 at 1 mm, moving bright skull inside the tables there took the marrow too (skull Dice
    0.882 -> 0.384). Gaussians below MARROW_MIN_SHARE of their class's weight are not counted."""
    above = _skull_above_brain(fit)
    return None if above is None or above >= 0 else skull_cut(fit)


def _skull_above_brain(fit) -> float | None:
    """The skull class's brightest live Gaussian mean less the brain class's darkest (`_live_means`), or None
    with fewer than two live skull Gaussians or no live brain Gaussian: > 0 a fat-bright marrow (`tables_cut`),
    < 0 a skull darker than the brain throughout (`csf_inside_cut`)."""
    skull, brain = _live_means(fit, Tissue.SKULL), _live_means(fit, Tissue.BRAIN)
    return None if skull.size < 2 or brain.size == 0 else float(skull.max() - brain.min())


def _live_means(fit, cls: Tissue) -> np.ndarray:
    """The means of class `cls`'s Gaussians in `fit` ((posteriors, EMResult, EMOptions, ...)) with at least
    MARROW_MIN_SHARE of the class's weight."""
    _, res, opts = fit[:3]
    means, weights = np.asarray(res.params.means), np.asarray(res.params.weights)
    return means[(weights >= MARROW_MIN_SHARE) & (np.asarray(opts.component_class) == int(cls))]


def _grown_tables(labels: np.ndarray, y, cut: float | None):
    """(skull, dark, tables) of `labels`: the skull-labelled voxels, those darker than `cut`, and those grown by
    one voxel (26-neighbourhood) within the skull: the compact tables, their one-voxel holes closed. None when
    `cut` is None or nothing is labelled skull."""
    skull = labels == Tissue.SKULL
    if cut is None or not skull.any():
        return None
    dark = skull & (np.asarray(y) < cut)
    return skull, dark, ndimage.binary_dilation(dark, np.ones((3, 3, 3), bool)) & skull


def bright_skull_inside_tables(labels: np.ndarray, y: np.ndarray, cut: float | None) -> np.ndarray:
    """Skull-labelled voxels at least as bright as `cut` from which one of the 26 grid rays (`enclosed`) reaches
    brain or CSF before a wall: CSF that the skull class took (`csf_inside_tables`). The rays pass only through
    such bright skull; everything else is a wall: the tables (skull darker than `cut`, grown by one voxel
    within the skull, as in `bright_skull_outside_tables`), scalp, background. A marrow between intact tables
    stays skull; bright skull on the brain's side of the inner table goes.

    Arguments:
        labels: (x, y, z) Tissue labels.
        y: (x, y, z) intensities on the scale of `cut`.
        cut: the tables' upper bound (`skull_cut`; None: nothing is found).
    Returns:
        (x, y, z) boolean.
    """
    labels = np.asarray(labels)
    if (split := _grown_tables(labels, y, cut)) is None:
        return np.zeros(labels.shape, bool)
    skull, _, tables = split
    bright = skull & ~tables
    inside = (labels == Tissue.BRAIN) | (labels == Tissue.CSF)
    return bright & ~enclosed(~bright & ~inside, inside)


def tables_cut(fit) -> float | None:
    """The intensity (bias-corrected EM data) between a skull's compact tables and its fat-bright marrow: the
    midpoint of the skull class's darkest and brightest Gaussian means of `fit` ((posteriors, EMResult,
    EMOptions, ...)). None unless the skull class has learnt a fat-bright marrow: its brightest Gaussian is
    brighter than the brain class's darkest (T1: fat, 0.8-1.4 of white matter, is brighter than grey matter,
    0.55-0.8, templates.MRI_CONTRAST_RANGE; compact bone and its partial volumes are darker). Gaussians
    below MARROW_MIN_SHARE of their class's weight are not counted."""
    above = _skull_above_brain(fit)
    return None if above is None or above <= 0 else skull_cut(fit)


#: the 6-neighbourhood (face-adjacent voxels)
_FACE = ndimage.generate_binary_structure(3, 1)


def marrow_tables(labels: np.ndarray, y: np.ndarray, cut: float | None, voxel_mm,
                  reach_mm: float = MARROW_TABLE_MM) -> np.ndarray:
    """The compact tables around a fat-bright marrow that the EM gave to CSF or the scalp (DEFAULT_MARROW_TABLES'
    comment): voxels labelled CSF or scalp, no brighter than `cut`, within `reach_mm` (Euclidean distance between
    voxel centres) of the exposed marrow: skull-labelled voxels brighter than `cut` that touch CSF or scalp across a
    face, with no skull-labelled table between. Where the tables are labelled skull the marrow is not exposed and
    nothing moves, however thin they are (a reach from all of the marrow took 1 mm of CSF beyond sharp 1 mm
    tables, session 33).

    Arguments:
        labels: (x, y, z) Tissue labels.
        y: (x, y, z) intensities on the scale of `cut` (the bias-corrected EM data).
        cut: the tables' upper bound (`tables_cut`); None: no fat-bright marrow, nothing found.
        voxel_mm: voxel sizes (3,), mm.
        reach_mm: a table's thickness, mm (> 0).
    Returns:
        (x, y, z) boolean.
    """
    if not (np.isfinite(reach_mm) and reach_mm > 0):
        raise ValueError(f"marrow_tables: `reach_mm` must be > 0 (mm), got {reach_mm}.")
    labels = np.asarray(labels)
    if cut is None:
        return np.zeros(labels.shape, bool)
    outside = (labels == Tissue.CSF) | (labels == Tissue.SCALP)
    exposed = (labels == Tissue.SKULL) & (y > cut) & ndimage.binary_dilation(outside, _FACE)
    if not exposed.any():
        return np.zeros(labels.shape, bool)
    candidates = outside & (y <= cut)
    # only the exposed marrow's neighbourhood: a distance transform on its bounding box grown by the reach
    pad = np.ceil(reach_mm / np.asarray(voxel_mm, np.float64)).astype(int)
    idx = np.nonzero(exposed)
    box = tuple(slice(max(int(i.min()) - p, 0), int(i.max()) + p + 1) for i, p in zip(idx, pad))
    out = np.zeros(labels.shape, bool)
    near = ndimage.distance_transform_edt(~exposed[box], sampling=voxel_mm) <= reach_mm
    out[box] = near & candidates[box]
    return out


def _marrow_tables(volume: Volume, fit, cfg: SegmentConfig):
    """`SegmentConfig.marrow_tables` on the final fit ((posteriors, EMResult, EMOptions, coords[, pi, sample])):
    the voxels `marrow_tables` finds get posterior one on the skull. Returns (posteriors, summary for the run
    report)."""
    post = fit[0]
    if skipped := _coarser_than_a_table(volume, "the tables are partial volume with the marrow"):
        return post, dict(voxels=0, skipped=skipped)
    cut = tables_cut(fit)
    if cut is None:
        return post, dict(voxels=0, skipped="the skull class learnt no fat-bright marrow (no Gaussian brighter than "
                                            "the brain's darkest)")
    labels = class_argmax(post)
    found = marrow_tables(labels, corrected_em_data(volume, fit, cfg), cut, voxel_sizes(volume.affine))
    summary = dict(voxels=int(found.sum()), from_csf=int((found & (labels == Tissue.CSF)).sum()),
                   from_scalp=int((found & (labels == Tissue.SCALP)).sum()), cut=round(float(cut), 4),
                   reach_mm=MARROW_TABLE_MM)
    if found.any():
        post = np.array(post, copy=True)
        post[:, found] = 0.0
        post[Tissue.SKULL, found] = 1.0
    log.info("segment (%s): tables around the marrow relabelled skull: %s", cfg.modality, summary)
    return post, summary


def bright_skull_outside_tables(labels: np.ndarray, y: np.ndarray, cut: float | None) -> np.ndarray:
    """Skull-labelled voxels at least as bright as `cut` (`tables_cut`) that the skull's tables do not enclose:
    scalp fat that the skull class took once it learnt the marrow's fat (`marrow_inside_skull`'s second half).
    A voxel is given back when one of its 26 grid rays (`enclosed`) reaches the way out before a wall. Walls:
    the tables (skull darker than `cut`, grown by one voxel within the skull), CSF, brain, background that tissue
    encloses. Way out: scalp that the skull does not enclose (`marrow_enclosed`'s complement: not marrow) and
    background that leads out of the grid. Marrow between two tables stays skull; fat outside the outer table
    goes. The growth closes one-voxel holes in a table, where partial volume with the marrow and the fat makes a
    thin table brighter than `cut`: without it, on the MNI152 head's adult-marrow 8 % scan of random contrast 2
    at 1 mm (experiments/results/segmentation_marrow_inside_skull.md, "Session 25") the marrow escaped through
    them (110,777 voxels given back, skull Dice 0.882 -> 0.330). A grown voxel that is not dark goes back with
    the fat it touches unless it also touches marrow that stays (a hole's voxel does).

    Arguments:
        labels: (x, y, z) Tissue labels.
        y: (x, y, z) intensities on the scale of `cut`.
        cut: the tables' upper bound (None: nothing is given back).
    Returns:
        (x, y, z) boolean.
    """
    labels = np.asarray(labels)
    if (split := _grown_tables(labels, y, cut)) is None:
        return np.zeros(labels.shape, bool)
    skull, dark, tables = split
    cube = np.ones((3, 3, 3), bool)
    held = enclosed_background(labels)
    wall = tables | held | (labels == Tissue.CSF) | (labels == Tissue.BRAIN)
    way_out = ((labels == Tissue.SCALP) & ~_marrow_enclosed(labels, held)) | ((labels == Tissue.BACKGROUND) & ~held)
    out = (skull & ~tables) & ~enclosed(wall, way_out)
    marrow = skull & ~tables & ~out
    # the grown voxels (bright, beside a table) go with the side they touch: back with the fat if they touch
    # fat given back and no marrow kept (a hole's voxel touches the marrow and stays)
    rim = tables & ~dark
    return out | (rim & ndimage.binary_dilation(out, cube) & ~ndimage.binary_dilation(marrow, cube))


def _layer_split(volume: Volume, priors: np.ndarray, unmodelled, pi, fit, cfg: SegmentConfig,
                 return_priors: bool = False, given_back=None):
    """The EM again on priors whose CSF/skull split is a step at the change point in depth learnt from
    the scan (`depth_prior.fit_layer_split` on the bias-corrected EM data, in the CSF + skull band of
    `fit`; `with_local_split`), after the learnt proportions `pi` (None: none) where the atlas models no
    bone; with `cfg.scalp_split_on()` its skull/scalp split too (`_scalp_split`, the same EM). `fit` is (posteriors, EMResult, EMOptions, coords[, pi, sample]) (with the sample its EM data is reused). `given_back`: the voxels whose skull prior
    `_marrow_inside_skull` gave to the scalp without running the EM (its `defer_mirror`), None: none; they count
    as scalp here, and the EM starts from its own start (the mirror's reason), not from `fit`'s parameters.
    Returns (`_classify_all`'s output, summary for the run report), and with `return_priors` the priors its EM
    ran on (float32, the proportions applied)."""
    t0 = time.perf_counter()
    post, res, opts, coords = fit[:4]
    labels = class_argmax(post)
    if given_back is not None:
        labels[given_back] = Tissue.SCALP
    _brain_and_scalp(labels, "layer_split")
    vox = voxel_sizes(volume.affine)
    # the depth's ends are compartments: the brain of the intracranial space (brain + CSF's largest component) and
    # the scalp's largest component, not stray labels (fat labelled brain in the scalp, scalp in the brain), which
    # put depth 0 or 1 beside them (session 33: 13,816 and 6,234 voxels on the benchmark's scan; the child's-marrow 1 mm table's rows 2 -> 3 of 4)
    brain = (labels == Tissue.BRAIN) & largest_component((labels == Tissue.BRAIN) | (labels == Tissue.CSF))
    if not brain.any():
        raise ValueError("[segment] layer_split: the largest connected piece of brain + CSF the first EM labelled "
                         "holds no brain voxel, so there is no intracranial space to measure depth from; check "
                         "the scan and `modality`, or set layer_split = false.")
    t = layer_depth(brain, largest_component(labels == Tissue.SCALP), vox)
    y = corrected_em_data(volume, fit, cfg)
    band = (labels == Tissue.CSF) | (labels == Tissue.SKULL)
    if not band.any():
        raise ValueError("[segment] layer_split: the first EM labelled no CSF and no skull voxel, so there is no "
                         "band to split; check the scan and `modality`, or set layer_split = false.")
    tau, summary = fit_layer_split(y, t, band, vox, LAYER_SPLIT_MM)
    if pi is not None:  # the proportions learnt where the atlas models no bone are kept, not re-learnt
        priors = with_proportions(priors, unmodelled, pi)
    # what the registered atlas expects of the band, beside what the split learnt (`csf_fraction`): where the
    # inner table is as dark as CSF the split can run into the bone (results/segmentation_layer_split.md)
    p_csf = float(np.asarray(priors[Tissue.CSF])[band].sum(dtype=np.float64))  # the band only, not a float64 copy
    p_skull = float(np.asarray(priors[Tissue.SKULL])[band].sum(dtype=np.float64))  # of the whole grid
    summary["atlas_csf_fraction"] = round(p_csf / max(p_csf + p_skull, 1e-30), 4)
    # started from the first EM's fit (only the CSF/skull priors changed): fewer iterations than from quantiles;
    # after a deferred mirror from the EM's own start, as the mirror's EM would have
    split_priors = with_local_split(priors, t, tau, LAYER_SPLIT_WIDTH)
    if cfg.scalp_split_on() and (skipped := _coarser_than_a_table(volume, "no table to find")):
        summary["scalp_split"] = dict(skipped=skipped)
    elif cfg.scalp_split_on():
        split_priors, summary["scalp_split"] = _scalp_split(labels, y, vox, split_priors)
    new = _classify(volume, split_priors, cfg, init=res.params if given_back is None else None, data=_fit_data(fit))
    new = new[:4] + (pi,) + new[5:]
    summary.update(window_mm=LAYER_SPLIT_MM, width=LAYER_SPLIT_WIDTH,
                   relabelled_fraction=round(float((class_argmax(new[0]) != labels).mean()), 4),
                   seconds=round(time.perf_counter() - t0, 1))
    log.info("segment (%s): CSF/skull split learnt from the scan's band: %s", cfg.modality, summary)
    return (new, summary, split_priors) if return_priors else (new, summary)


def _scalp_split(labels: np.ndarray, y: np.ndarray, vox, priors: np.ndarray) -> tuple[np.ndarray, dict]:
    """`SegmentConfig.scalp_split`: the skull/scalp change point in depth t between the brain + CSF of `labels` (0)
    and the background that leads out of the grid (1; `enclosed_background`'s complement), learnt from `y` in the
    skull + scalp band as `fit_layer_split` learns the CSF/skull one (brain + CSF: its largest component), and `priors`' skull + scalp mass shared by a
    step at it (LAYER_SPLIT_WIDTH). Returns (the priors, float32; summary for the run report)."""
    air = (labels == Tissue.BACKGROUND) & ~enclosed_background(labels)
    # the intracranial compartment, not every brain or CSF voxel: stray brain labels in the scalp's fat (T1-bright
    # like white matter) put depth 0 in the scalp and drew the change point into the fat (session 33)
    inner = largest_component((labels == Tissue.BRAIN) | (labels == Tissue.CSF))
    band = (labels == Tissue.SKULL) | (labels == Tissue.SCALP)
    if not (air.any() and inner.any() and band.any()):
        return priors, dict(skipped="no air around the head, or no brain + CSF, or no skull + scalp labelled")
    t = layer_depth(inner, air, vox)
    tau, summary = fit_layer_split(y, t, band, vox, LAYER_SPLIT_MM)
    summary["skull_fraction"] = summary.pop("csf_fraction")  # the inner side's share of the band: skull here
    return with_local_split(priors, t, tau, LAYER_SPLIT_WIDTH, (Tissue.SKULL, Tissue.SCALP)), summary


def config_atlas(cfg: SegmentConfig) -> Atlas:
    """The atlas `segment` uses with `cfg` when given none: `default_atlas` of its modality,
    `atlas`, `atlas_voxel_mm` and `atlas_subjects` (built once, then cached on disk)."""
    return default_atlas(cfg.modality, atlas=cfg.atlas, voxel_mm=cfg.atlas_voxel_mm,
                         n_subjects=cfg.atlas_subjects)


def segment(volume: Volume, atlas: Atlas | None = None, cfg: SegmentConfig = SegmentConfig()) -> LabelMap:
    """Segment a head MRI or CT into BACKGROUND, BRAIN, CSF, SKULL and SCALP.

    `segment_reported` returns the fitted model (posteriors, registration, mixture) too.

    Arguments:
        volume: the scan (MRI: magnitude, arbitrary units; CT: Hounsfield units).
        atlas: an Atlas of the same modality; None uses `default_atlas(cfg.modality)` (cached).
        cfg: SegmentConfig.
    Returns:
        LabelMap of Tissue values (BACKGROUND, BRAIN, CSF, SKULL, SCALP) on the scan's grid.
    """
    labels, report = segment_reported(volume, atlas, cfg)
    log.info("segmented with the %s atlas: %d EM iterations (converged: %s)", report.atlas_name,
             report.n_iter, report.converged)
    return labels


def bone_majority(hu: np.ndarray, posteriors: np.ndarray) -> tuple[np.ndarray, dict]:
    """CT: relabel the bone surface by the partial-volume majority rule (posteriors changed in place of a copy).

    A voxel on the boundary of bone (intensity B) and soft tissue (S) holding a bone fraction f has
    HU = f B + (1 - f) S, so bone fills most of it iff HU > (B + S) / 2. A Gaussian mixture cannot
    draw that line: the skull class's broad Gaussians (diploe, partial-volume tail) own every voxel
    from ~150 HU up, so the EM's skull is a voxel too thick at 2 mm; and a broad CSF or scalp
    Gaussian can own bone voxels next to it. Bone is unambiguous in CT, so after the EM:

    - B = median HU of the voxels the EM labels skull, S = median HU of those it labels brain (the
      soft tissue on either side of the skull is 0-60 HU; brain is the largest and surest of it);
      the threshold T = (B + S) / 2, both learnt from the scan (any scanner's calibration);
    - every head voxel (not labelled background) above T is skull;
    - skull voxels at or below T go to their most probable other class where they form a connected
      piece (6-neighbourhood) that touches soft tissue (head voxels labelled neither skull nor
      background): the partial-volume shell of the bone surface; pieces enclosed by bone above T
      keep the skull label (diploe, fatty marrow of 300-800 HU in real skulls).

    Arguments:
        hu: (x, y, z) the CT in Hounsfield units.
        posteriors: (5, x, y, z) class posteriors from the EM.
    Returns:
        (posteriors with the rule applied (one-hot where it decided), dict of B, S, T and voxel counts
        moved), or the input and an empty dict when the EM labelled no skull or no brain.
    """
    lab = class_argmax(posteriors)
    sk, br = lab == int(Tissue.SKULL), lab == int(Tissue.BRAIN)
    if not sk.any() or not br.any():
        return posteriors, {}
    b, s = float(np.median(hu[sk])), float(np.median(hu[br]))
    if not b > s:  # no bright bone: not a CT the rule describes
        return posteriors, {}
    t = 0.5 * (b + s)
    head = lab != int(Tissue.BACKGROUND)
    bone = head & (hu > t)
    skull = sk | bone
    soft = head & ~skull
    # skull voxels at or below T in a connected piece that touches soft tissue: partial volume at the
    # bone surface (dropped); pieces enclosed by bone above T: diploe (kept)
    post = np.array(posteriors, copy=True)
    others = post.sum(0) - post[int(Tissue.SKULL)]
    drop = _pieces_touching(skull & ~bone, soft) & (others > 1e-6)  # (no other class possible: keep skull)
    post[:, bone] = 0.0
    post[int(Tissue.SKULL), bone] = 1.0
    post[int(Tissue.SKULL), drop] = 0.0
    z = post[:, drop].sum(0)
    post[:, drop] /= np.maximum(z, np.finfo(post.dtype).tiny)
    info = dict(bone_hu=b, soft_hu=s, threshold_hu=t, added=int((bone & ~sk).sum()), removed=int(drop.sum()))
    return post, info


def _pieces_touching(mask: np.ndarray, other: np.ndarray) -> np.ndarray:
    """The voxels of `mask` in connected pieces (6-neighbourhood) with a voxel beside `other`
    (6-neighbourhood): the partial-volume shell a majority rule relabels."""
    pieces, _ = ndimage.label(mask)
    touches = np.unique(pieces[ndimage.binary_dilation(other) & mask])
    return np.isin(pieces, touches[touches > 0])


def air_majority(hu: np.ndarray, posteriors: np.ndarray) -> tuple[np.ndarray, dict]:
    """CT: relabel the skin's partial-volume shell by the majority rule (posteriors changed in a copy).

    A voxel on the boundary of air (intensity A, -1000 HU) and soft tissue (S) holding a tissue fraction
    f has HU = f S + (1 - f) A, so air fills most of it iff HU < (A + S) / 2. The EM cannot draw that
    line: the background class's Gaussians are as narrow as the scanner's noise around A, so a voxel
    with any tissue in it lies tens of sd from them and goes to the scalp class's broad tail Gaussian;
    the EM's scalp is then the whole skin shell too thick (on the phantom at 2 mm, 11k voxels of median
    -734 HU labelled scalp). After the EM:

    - A = median HU of the background voxels beside the scalp (the air the skin borders, not a
      scanner's padding outside its field of view), S = median HU of the voxels labelled scalp,
      T = (A + S) / 2, all learnt from the scan (any scanner's calibration);
    - scalp voxels below T go to background where they form a connected piece (6-neighbourhood) that
      touches background: the shell at the skin (and at the walls of air cavities the EM labels
      background). Pieces enclosed by tissue keep their label.

    Arguments:
        hu: (x, y, z) the CT in Hounsfield units.
        posteriors: (5, x, y, z) class posteriors from the EM.
    Returns:
        (posteriors with the rule applied (one-hot where it decided), dict of A, S, T and voxels
        moved), or the input and an empty dict when the EM labelled no background or no scalp, or the
        scalp is not brighter than the background (not a CT the rule describes).
    """
    lab = class_argmax(posteriors)
    bg, sc = lab == int(Tissue.BACKGROUND), lab == int(Tissue.SCALP)
    if not bg.any() or not sc.any():
        return posteriors, {}
    # the air next to the scalp: a CT's padding outside its reconstruction circle (-2048 or -3024 HU on
    # many scanners) is background too, but not the air the skin borders
    near = bg & ndimage.binary_dilation(sc)
    a, s = float(np.median(hu[near if near.any() else bg])), float(np.median(hu[sc]))
    if not s > a:
        return posteriors, {}
    t = 0.5 * (a + s)
    drop = _pieces_touching(sc & (hu < t), bg)
    post = np.array(posteriors, copy=True)
    post[:, drop] = 0.0
    post[int(Tissue.BACKGROUND), drop] = 1.0
    return post, dict(air_hu=a, scalp_hu=s, threshold_hu=t, removed=int(drop.sum()))


def enclosed(wall: np.ndarray, escape: np.ndarray) -> np.ndarray:
    """Voxels from which every one of the 26 grid rays (along the axes, face and body diagonals) meets
    `wall` before `escape` or the grid's edge (a `wall` voxel counts as enclosed).

    Each ray is followed by one sweep of the grid against it (slice by slice along an axis the ray
    moves on, each slice reading the next one shifted by the ray's other steps), so the cost is 26
    passes over the grid, not one per voxel and ray; the rays are shared between two threads (NumPy's
    logical operations release the GIL).

    Arguments:
        wall, escape: (x, y, z) boolean masks (disjoint; `wall` wins where both are set).
    Returns:
        (x, y, z) boolean.
    """
    wall, escape = np.asarray(wall, bool), np.asarray(escape, bool)
    if wall.shape != escape.shape or wall.ndim != 3:
        raise ValueError(f"enclosed: `wall` {wall.shape} and `escape` {escape.shape} must be 3-D masks of one grid.")
    open_ = ~escape
    steps = [step for step in itertools.product((-1, 0, 1), repeat=3) if any(step)]
    with ThreadPoolExecutor(2) as pool:
        half = list(pool.map(lambda group: _enclosed_along(wall, open_, group), (steps[0::2], steps[1::2])))
    return half[0] & half[1]


def _enclosed_along(wall: np.ndarray, open_: np.ndarray, steps) -> np.ndarray:
    """`enclosed` for the rays `steps` only (`open_` = not escape)."""
    inside = np.ones(wall.shape, bool)
    for step in steps:
        a = next(i for i in range(3) if step[i])  # sweep along the first axis the ray moves on
        w, o = np.moveaxis(wall, a, 0), np.moveaxis(open_, a, 0)
        hit = np.empty(w.shape, bool)
        dy, dz = (step[i] for i in range(3) if i != a)
        ny, nz = w.shape[1:]
        src = (slice(max(dy, 0), ny + min(dy, 0)), slice(max(dz, 0), nz + min(dz, 0)))  # slice i + step, shifted
        dst = (slice(max(-dy, 0), ny + min(-dy, 0)), slice(max(-dz, 0), nz + min(-dz, 0)))
        order = range(len(w) - 1, -1, -1) if step[a] > 0 else range(len(w))
        ahead = np.zeros((ny, nz), bool)  # beyond the edge, and where the shift reads past a side: escaped
        prev = None
        for i in order:
            if prev is not None:
                ahead[dst] = hit[prev][src]
            np.logical_and(o[i], ahead, out=hit[i])
            np.logical_or(hit[i], w[i], out=hit[i])
            prev = i
        inside &= np.moveaxis(hit, 0, a)
    return inside


def scalp_outside_skull(posteriors: np.ndarray, y: np.ndarray, params: MixtureParams,
                        opts: EMOptions) -> tuple[np.ndarray, dict]:
    """CT: scalp lies outside the skull. Scalp-labelled voxels that the segmented skull encloses on every
    side (`enclosed`: all 26 grid rays meet skull before background or the grid's edge), in connected
    pieces (6-neighbourhood) beside the brain or CSF, and whose intensity the EM's mixture does not
    explain best as scalp (the class of highest likelihood at the fitted Gaussians, no prior), lose
    their scalp posterior (the rest renormalised), so each goes to its next most probable class (a
    copy; one-hot nowhere).

    Why: where the registered atlas puts its face or skull base on intracranial tissue (a head whose
    cranium reaches lower than the atlas's, as in our phantom family, whose brain lies where the mni152
    atlas has its face), the EM labels brain scalp: on CT, brain (30-40 HU) and the face's muscle (40-60
    HU) are one intensity, and only the prior separates them. On CT the bone is unambiguous, so the skull
    the EM segments is a reliable wall; a real head's scalp, face and neck lie outside it or reach the
    outside through its openings (orbits, nasal cavity, foramen magnum), and the pockets a skull base
    does enclose (mastoid air cells, sinuses) are walled off from the brain by bone. Nothing here is a
    constant of a head: "every ray" and "beside brain or CSF" are the definition of inside the cranium.
    The likelihood condition keeps what the prior got right where a skull base encloses soft tissue or
    air next to the brain at the grid's resolution: on the ANTs head at 2 mm, pockets of air (about
    -550 HU) and fat (-15 to -30 HU) by the skull base, true scalp or air, which without it went to CSF
    (CSF Dice -0.005 to -0.007).

    Arguments:
        posteriors: (5, x, y, z) class posteriors.
        y: (x, y, z) the EM's data (CT: its HU after `denoise`, bias removed where there is one).
        params, opts: the EM's fitted MixtureParams and its EMOptions (component classes).
    Returns:
        (posteriors, dict of voxels relabelled, in all and per class they went to). Voxels whose only
        class is scalp (no other posterior) keep it.
    """
    lab = class_argmax(posteriors)
    sc = lab == int(Tissue.SCALP)
    info = dict(relabelled=0)
    if not sc.any() or not (lab == int(Tissue.SKULL)).any():
        return posteriors, info
    cand = sc & enclosed(lab == int(Tissue.SKULL), lab == int(Tissue.BACKGROUND))
    cand &= posteriors.sum(0) - posteriors[int(Tissue.SCALP)] > 1e-6
    drop = _pieces_touching(cand, (lab == int(Tissue.BRAIN)) | (lab == int(Tissue.CSF))) if cand.any() else cand
    if drop.any():  # of those, the voxels whose intensity is not most likely scalp's
        at = np.nonzero(drop)
        yc = jnp.asarray(np.asarray(y, np.float64)[at].reshape(-1, 1, 1), jnp.float32)
        flat = replace(opts, beta=0.0, relax=0.0, bias_degree=0)
        lik = infer_posteriors(yc, jnp.ones((opts.n_classes,) + yc.shape, yc.dtype), params, flat, 0)
        drop[at] = np.asarray(jnp.argmax(lik, axis=0)).ravel() != int(Tissue.SCALP)
    if not drop.any():
        return posteriors, info
    post = np.array(posteriors, copy=True)
    post[int(Tissue.SCALP), drop] = 0.0
    post[:, drop] /= post[:, drop].sum(0)
    to = class_argmax(post[:, drop])
    info = dict(relabelled=int(drop.sum()), **{Tissue(k).name.lower(): int((to == k).sum()) for k in np.unique(to)})
    return post, info


def _coords(shape, padded, stride, dtype):
    """Bias-basis coordinates of a padded grid: [-1, 1] spans the scan itself (the padding lies past 1)."""
    return tuple(
        jnp.asarray(2.0 * np.arange(0, p, stride) / max(n - 1, 1) - 1.0, dtype=dtype) for n, p in zip(shape, padded)
    )
