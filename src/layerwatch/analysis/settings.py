"""Analysis settings (config section ``[analysis]``)."""

from __future__ import annotations

from typing import Literal

from pydantic import Field

from layerwatch.settings_base import Section

__all__ = ["AnalysisSettings", "METRIC_NAMES", "SceneSettings"]

METRIC_NAMES = (
    "cosine",
    "sqeuclidean",
    "pearson",
    "spearman",
    "kendall",
    "jaccard",
    "dice",
    "l1",
    "euclidean",
    "hellinger",
    "sorensen",
    "clark",
)


class AnalysisSettings(Section):
    """HOG parameters, similarity measure, block threshold and the blocks that count (section ``[analysis]``).

    The built-in values are the paper's (cosine, T_S 0.7, 8-px cells in 2x2
    blocks, 9 bins, 5 mm footprint margin, no pre-filter). Every verb runs
    the evaluation's recommended values over them unless ``--paper-settings``
    is given: jaccard, T_S 0.20, margin 0 mm, ``presmooth_px`` 1.25,
    ``flat_tolerance`` 1.5, ``grow_threshold`` 0.2, ``grow_margin_mm`` 5,
    ``register_mm`` 0.6, ``off_colour`` on (:data:`layerwatch.pipeline.config.RECOMMENDED`; ``layerwatch config show``
    prints the values in force and their sources).

    Attributes
    ----------
    metric : str
        Similarity measure of Table 2 (:data:`METRIC_NAMES`); default ``"cosine"``.
    threshold : float
        Block threshold T_S in [0, 1]: a block below it is anomalous; default 0.7.
    cell_px, block_cells, bins, block_norm, gamma
        HOG cell side (px), block side (cells), orientation bins, block
        normalisation, square-root gamma (skimage's parameters).
    footprint_margin_mm : float
        Blocks within this distance of the layer's footprint count, mm; default 5.
    min_region_blocks : int
        Smallest group of anomalous blocks kept.
    min_gradient, flat_tolerance, votes, presmooth_px, grow_threshold, grow_margin_mm, register_mm, off_colour
        See the comments at each field below.

    References
    ----------
    Petsiuk & Pearce (2022), Section 2.4 (8 px, 2x2, 9 bins, 70 %).
    """

    metric: Literal[METRIC_NAMES] = "cosine"  # type: ignore[valid-type]
    threshold: float = Field(0.7, ge=0, le=1)
    cell_px: int = Field(8, ge=2, le=64)
    block_cells: int = Field(2, ge=1, le=8)
    bins: int = Field(9, ge=2, le=36)
    block_norm: Literal["L2-Hys", "L2", "L1", "L1-sqrt"] = "L2-Hys"
    footprint_margin_mm: float = Field(5.0, ge=0)
    min_region_blocks: int = Field(1, ge=1)
    # Block pairs whose mean gradient magnitude (grey levels per pixel, 0-255
    # scale, central differences) is below this in BOTH images are featureless
    # (similarity 1), so sensor noise (sigma up to ~2.5 levels) on a bare bed
    # matches an empty reference.
    min_gradient: float = Field(5.0, ge=0)
    # The same rule with tolerance for what the camera may not resolve: a pair
    # also counts as featureless when the PHOTO's block is below min_gradient
    # and the REFERENCE's below flat_tolerance x min_gradient (faint bead
    # lines the renderer draws and the photo does not show are no failure;
    # block normalisation would turn them into unrelated histograms). Texture
    # in the photo where the reference is flat is always compared: that is
    # what a hole, an object or strands look like. 1 = both below min_gradient.
    flat_tolerance: float = Field(1.0, ge=1.0, le=10.0)
    gamma: bool = False
    # What an anomalous block adds to S_A of eq. (5): "tiles" (the paper) its
    # whole tile (one cell, where the overlapping blocks are centred), even
    # when the tile lies beside the printed layer and the block is considered
    # only because one of its cells touches the footprint; "printed" only the
    # printed part of its tile (the footprint's share of it), so a% is the
    # anomalous share of the printed area and what lies beside it is
    # outside_area_mm2, its own figure. On a 45-degree camera the tiles along
    # a wall's edge show what lies below the layer (a floor through an
    # opening, the wall's own face), which the reference draws least well.
    # "part": a tile holding a printed pixel (or inside the part) counts
    # whole, only the tiles wholly beside the part count nothing.
    anomalous_area: Literal["tiles", "part", "printed"] = "tiles"
    # How a gradient votes (:mod:`layerwatch.analysis.hog`): "one_bin"
    # (skimage, the paper); "split_ties": a gradient exactly on the 0/180-
    # degree bin edge (a rendered reference's straight edge along the top
    # view's columns) votes half into the first and half into the last bin,
    # so the photo's same edge, tilted by a fraction of a degree into the
    # last bin, still matches it; "interpolated": every vote split between
    # the two nearest bin centres.
    votes: Literal["one_bin", "split_ties", "interpolated"] = "one_bin"
    # Gaussian pre-filter (sigma, top-view px) of both images before the HOG:
    # removes sensor noise and the moire a warped photo shows above the
    # camera's resolvable frequency; 0 = the paper's unfiltered images.
    presmooth_px: float = Field(0.0, ge=0, le=5)
    # Hysteresis for the failing area drawn on the overlay (localisation):
    # blocks below threshold + grow_threshold that touch (8-neighbourhood) an
    # anomalous block are drawn with it. a%, the regions and so the pause
    # policy still count only blocks below the threshold.
    grow_threshold: float = Field(0.0, ge=0, le=1)
    # How far beside the footprint a drawn region may grow (spaghetti, a
    # displaced part); regions still have to start on the considered blocks.
    # Values below footprint_margin_mm mean the footprint margin.
    grow_margin_mm: float = Field(0.0, ge=0)
    # Registration before the comparison: a residual shift of the photo's top
    # view against the reference up to this size (a camera mount that moved
    # by a pixel or two) is measured on the print's box and undone
    # (:mod:`layerwatch.analysis.view_shift`); a larger one is left alone (a
    # real displacement). mm on the layer plane; 0 = off (the paper).
    register_mm: float = Field(0.0, ge=0, le=5)
    # The off-colour test on the printed layer (:mod:`layerwatch.analysis.part_colour`):
    # blocks whose tile is mostly another material than the part's filament
    # (its colour measured on the footprint in the same photo, so exposure and
    # white balance cancel) count as anomalous, whatever their gradients. An
    # object with the part's texture scale but another colour (a blue hex key
    # across infill lines) passes the HOG test. False = the paper's method.
    off_colour: bool = False


class SceneSettings(Section):
    """The image-space scene channel (config section ``[scene]``, :mod:`layerwatch.analysis.scene_change`).

    Off in the built-in (paper) values, on in the recommended ones
    (:data:`layerwatch.pipeline.config.RECOMMENDED`), so ``--paper-settings``
    reproduces the paper's single-photo method.

    Attributes
    ----------
    enabled : bool
        Compare every photo with the expected appearance of the scene outside
        the layer's predicted change (default False: the paper's method).
    working_px : int
        Long side of the working image the camera frame is reduced to, px
        (640: a 1080p frame is averaged 3 x 3, a 720p one 2 x 2).
    margin_mm : float
        Dilation of the layer's footprint before it is projected into the
        image: half a bead, the wall's bulge and the thin shadow line at its
        foot, mm.
    block_px : int
        Side of a change block in working-image px (8 px ~ 2 mm on the bed for
        a 90 mm square seen by a 720p/1080p camera).
    noise_k : float
        Block threshold = median + ``noise_k`` x 1.4826 MAD of the frame's
        block scores (the noise estimate of that frame), grey levels.
    min_change : float
        Lowest block threshold, grey levels (0-255) of mean absolute residual.
    min_region_mm2 : float
        Smallest changed region reported, mm^2 on the layer plane.
    max_changed_share : float
        A frame whose changed blocks exceed this share of the scored blocks
        does not show the scene the model expects (camera moved, covered,
        light switched): it is rejected as a camera fault, never a failure.
    shadow_reach : float
        How far from the printed body a change may still be the part's own cast shadow, in heights of
        the print (the cotangent of the lowest lamp elevation allowed for: 2 is 27 deg); such a change
        is judged by :mod:`layerwatch.analysis.cast_shadow` (grey, within a shadow's range, texture
        kept, one way, not the whole block unless under a roof of the part: a bridge, an overhang) and
        not counted when it is shade. Default 2 (since session 22): real lamps throw the part's shadow
        beside it, and on Blender Cycles photos of clean prints those shadows were the changes beside the
        print and a pause (docs/evaluation/README.md, sessions 20-22). Its price on the raster simulator,
        which draws no cast shadows: Simplify3D series spaghetti AUROC 0.992 -> 0.947 (strands of the
        part's colour on its first millimetres, on a floor just printed, taken as shade). 0 turns it off.
    """

    enabled: bool = False
    working_px: int = Field(640, ge=160, le=4096)
    margin_mm: float = Field(1.5, ge=0, le=20)
    block_px: int = Field(8, ge=2, le=64)
    noise_k: float = Field(6.0, gt=0, le=100)
    min_change: float = Field(8.0, ge=0, le=255)
    min_region_mm2: float = Field(4.0, ge=0)
    max_changed_share: float = Field(0.35, gt=0, le=1)
    shadow_reach: float = Field(2.0, ge=0, le=20)
