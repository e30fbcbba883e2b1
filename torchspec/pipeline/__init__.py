"""The fit: SVBRDF maps from a capture (``torchspec fit``), one module per stage.

Per tile of pixels (all frames of a tile at once, so memory is bounded by the tile):

1. :mod:`~torchspec.pipeline.start`: masks of non-finite, saturated and shadowed samples come
   from the whole stack (:func:`torchspec.start.photometric.sample_masks`); robust photometric stereo
   gives the normal and ``k_d``; pixels whose residual peaks above the noise get a specular start
   (:mod:`torchspec.start.specular`);
2. :mod:`~torchspec.pipeline.solver`: batched Levenberg-Marquardt of one model on a set of pixels;
3. :mod:`~torchspec.pipeline.uncertainty`: the sensor's noise, each fit's chi-square and
   standard deviations;
4. :mod:`~torchspec.pipeline.selection`: each pixel's model by the information criterion,
   climbing ``FitConfig.ladder.models`` only where the smaller model leaves a residual above the noise;
5. :mod:`~torchspec.pipeline.checks`: flags (:mod:`torchspec.pipeline.flags`) and quality;

run by :mod:`~torchspec.pipeline.tile` (a :class:`~torchspec.pipeline.tile.TileResult`). Over
the whole image, :mod:`~torchspec.pipeline.assembly` joins the tiles into a :class:`Fit`
(:mod:`~torchspec.pipeline.result`), after :mod:`~torchspec.pipeline.smoothing` with
``FitConfig.ladder.smooth``. Two drivers run the tiles: :func:`fit` in this process
(:mod:`~torchspec.pipeline.in_process`) and :func:`fit_on_cluster` on a Dask cluster
(:mod:`~torchspec.pipeline.cluster`); both plan the fit alike (:mod:`~torchspec.pipeline.plan`),
decide by one policy whether its lights are calibrated from the photographs
(:mod:`~torchspec.pipeline.calibration`: in this process; a cluster refuses such a fit) and share
the checkpoint format (:mod:`~torchspec.pipeline.checkpoint`). The settings:
:mod:`~torchspec.pipeline.settings` (:class:`FitConfig`, grouped by stage: ``masks``, ``start``,
``ladder``, ``term``, ``flags``, ``quadrature``, ``compute``, ``lm``).
"""

from .checkpoint import FitInterrupted
from .checks import Checks
from .cluster import ClusterError, connect, fit_on_cluster
from .in_process import fit
from .plan import FitWarning
from .result import Fit, write_fit
from .selection import ModelFit
from .settings import (
    AUTO,
    COMPILE_PIXELS,
    INITS,
    LADDER,
    MODEL_CODES,
    ComputeConfig,
    FitConfig,
    FlagsConfig,
    LadderConfig,
    MasksConfig,
    QuadratureConfig,
    StartConfig,
    TermConfig,
    select_frames,
)
from .smoothing import smooth_choice
from .start import StartingPoint, starting_point
from .tile import TileResult

__all__ = [
    "AUTO",
    "COMPILE_PIXELS",
    "INITS",
    "LADDER",
    "MODEL_CODES",
    "Checks",
    "ClusterError",
    "ComputeConfig",
    "Fit",
    "FitConfig",
    "FitInterrupted",
    "FitWarning",
    "FlagsConfig",
    "LadderConfig",
    "MasksConfig",
    "ModelFit",
    "QuadratureConfig",
    "StartConfig",
    "StartingPoint",
    "TermConfig",
    "TileResult",
    "connect",
    "fit",
    "fit_on_cluster",
    "select_frames",
    "smooth_choice",
    "starting_point",
    "write_fit",
]
