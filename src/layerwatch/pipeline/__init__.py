"""layerwatch.pipeline: the one per-layer pipeline every driver calls.

- :mod:`~layerwatch.pipeline.config` -- ``JobConfig`` (the job's settings) and
  ``resolve_config``, the one settings resolver (defaults -> recommended ->
  dashboard -> G-code -> job file -> flags, with the source of every value).
- :mod:`~layerwatch.pipeline.step` -- ``LayerPipeline``: the job context
  (toolpath, camera pose, top view of the bed, settings) and the per-layer
  step ``process(photo, layer) -> LayerResult`` (photo -> top view ->
  reference -> comparison -> typed record), with the frame-quality hook.
- :mod:`~layerwatch.pipeline.policy` -- ``PausePolicy`` and its ``Decision``.

The typed per-layer record is :class:`layerwatch.analysis.result.LayerResult`
(re-exported here): the comparison stage below the pipeline fills it first,
so it is defined there; the pipeline, the policy, storage, web and reports
share that one dataclass.

Drivers (``monitor``, ``analyze``, ``compare``, the demo, the evaluation)
import from the submodules; this package's ``__init__`` imports nothing heavy.
"""

from layerwatch.analysis.result import LayerResult, Region

__all__ = ["LayerResult", "Region"]
