"""Settings of the checks around the layer comparison (config sections ``[bed_check]``, ``[first_layer]``, ``[extrusion]``).

Each check is off in the built-in (paper) values and on in the recommended
ones (:data:`layerwatch.pipeline.config.RECOMMENDED`), like the scene
channel, so ``--paper-settings`` reproduces the paper's method. The bed check
and the first-layer inspection need the empty-bed photo (``calibrate
--markers`` keeps it, ``--bed-photo``); without one they do not run.
"""

from __future__ import annotations

from pydantic import Field

from layerwatch.settings_base import Section

__all__ = ["BedCheckSettings", "ExtrusionSettings", "FirstLayerSettings"]


class BedCheckSettings(Section):
    """The empty-bed check at job start (:mod:`layerwatch.analysis.bed_check`).

    Attributes
    ----------
    enabled : bool
        Compare the bed at job start with the empty-bed photo and hold the job
        when something lies on it (default False: the paper's method; on in
        the recommended settings).
    min_area_mm2 : float
        Changed area on the bed (mm^2, bed plane) from which the bed counts as
        occupied: a 10 mm hex key covers about 15 mm^2.
    block_px : int
        Side of a change block, top-view px (8 px = 1.2 mm at 6.67 px/mm).
    noise_k : float
        Block threshold = median + ``noise_k`` x 1.4826 MAD of the block scores, grey levels.
    min_change : float
        Lowest block threshold, grey levels (mean absolute residual after the light is fitted).
    max_changed_share : float
        More than this share of the observed bed changed: the view does not
        match the bed photo (camera moved, covered, light switched); the bed is
        reported as not checked (an alert, never a hold).
    """

    enabled: bool = False
    min_area_mm2: float = Field(8.0, ge=0, le=2500)
    block_px: int = Field(8, ge=2, le=64)
    noise_k: float = Field(6.0, gt=0, le=100)
    min_change: float = Field(8.0, ge=0, le=255)
    max_changed_share: float = Field(0.5, gt=0, le=1)


class FirstLayerSettings(Section):
    """The first-layer inspection (:mod:`layerwatch.analysis.first_layer`).

    Attributes
    ----------
    enabled : bool
        Check the photo of the first layer against its G-code and the empty
        bed (default False; on in the recommended settings).
    min_coverage : float
        Share of the first layer's footprint (in [0, 1]) where the photo must
        differ from the empty bed (new material); below it the layer failed.
    max_missing_mm2 : float
        Largest connected area of the footprint left like the empty bed (a
        missing line, a lifted or unstuck corner), mm^2.
    margin_mm : float
        Erosion of the footprint before it is judged (the bead's rounded edge), mm.
    min_change : float
        Lowest grey-level residual of a block that counts as new material.
    """

    enabled: bool = False
    min_coverage: float = Field(0.85, ge=0, le=1)
    max_missing_mm2: float = Field(12.0, ge=0, le=2500)
    margin_mm: float = Field(0.6, ge=0, le=10)
    min_change: float = Field(6.0, ge=0, le=255)


class ExtrusionSettings(Section):
    """The nothing-extruded check, layer to layer (:mod:`layerwatch.analysis.extrusion`).

    Attributes
    ----------
    enabled : bool
        Flag layers on which the G-code adds plastic and the photo shows none
        (default False; on in the recommended settings).
    min_similarity : float
        Median block NCC of the layer's top surface against the photo two
        layers back from which the last two layers added nothing. Chosen on
        the simulator (1280 x 720 camera, ``benchmarks/eval_checks.py --seed 0``):
        clean layers reached 0.79, the second layer of a nothing-extruded run
        was above 0.865 in 95 % of the runs (the rest: a moving light's
        highlights on a shiny top surface). A sharper high pass (0.7 px) with
        0.70 separated seed 0 better but gave a false alarm on seed 1.
    min_area_mm2 : float
        Layers whose footprint (eroded by ``margin_mm``) is smaller are judged together with
        the layer before them (:data:`layerwatch.pipeline.checks.POOL_BELOW_BLOCKS`), mm^2.
    margin_mm : float
        Erosion of the layer's footprint before it is projected into the image
        (the beads' rounded edges and the wall below them), mm.
    working_px : int
        Long side of the image the texture is compared on, px; the photo's own
        resolution up to this (bead lines 0.4-0.5 mm apart must be resolved:
        the scene channel's 640 px blur them into the same texture every layer).
        1280: the size the check's thresholds were chosen and evaluated at
        (720p photos); a 1080p photo is compared at that size too (a farm
        printer then holds 3.3 MB for the check instead of 7.4).
    block_px : int
        Block side of the comparison, px of that image.
    still_similarity : float
        A layer whose similarity is at least this (and below
        ``min_similarity``) is flagged too when at least ``still_share`` of
        its blocks fit the photo two layers back better in place than moved
        by the parallax of the two layers' height: the surface did not rise
        (:func:`~layerwatch.analysis.extrusion.still_share`). Chosen on the
        simulator (seed 1 and the window part's clean prints of seeds
        1100-1103): clean layers reached a share of 0.72 at similarities of
        0.26 or less, the second layer of a nothing-extruded run had 0.78 or
        more with a share of 0.74 or more. 1: off.
    still_share : float
        See ``still_similarity``.
    sure_similarity : float
        From this similarity on a layer is flagged on its similarity alone. Between ``min_similarity``
        and this, only when the surface did not rise either (the ``still_share`` test); where the camera
        sees less than a pixel of the layers' parallax, not at all (a 640 x 360 camera, 2 px a bed mm: a
        clean KISSlicer print paused at 0.85-0.89 before session 22, docs/checks.md): a twin layer (the
        same infill direction two layers up) can look as alike as a surface nothing was added to (0.86 on
        the window part's floor in Blender Cycles photos at 640 px, a pause on a clean print), while the second layer of a nothing-extruded run was above
        0.89 in 95 % of the simulator's runs (seed 1; the two runs the rise test alone missed, on the mini
        cube, were at 0.93 and 0.96). 1: the rise test applies to every similarity.
    """

    enabled: bool = False
    min_similarity: float = Field(0.84, ge=0, le=1)
    min_area_mm2: float = Field(10.0, ge=0, le=2500)
    margin_mm: float = Field(0.3, ge=0, le=10)
    working_px: int = Field(1280, ge=160, le=4096)
    block_px: int = Field(16, ge=2, le=64)
    still_similarity: float = Field(0.5, ge=0, le=1)
    still_share: float = Field(0.8, ge=0, le=1)
    sure_similarity: float = Field(0.9, ge=0, le=1)
