"""Deep matrix factorization of the observed rotation blocks (Sec. IV-B to IV-D).

:mod:`.dense` is the paper's fit (Adam), :mod:`.sparse` the L-BFGS fit for chain-like
graphs (:mod:`.precondition` its preconditioner), :mod:`.vanilla` ablation (c);
:mod:`.common` holds what they share. The options
are :class:`~rotavg_ros.core.options.DenseFitOptions` and
:class:`~rotavg_ros.core.options.SparseFitOptions`; :class:`FitSpec` carries what differs
between the fits of one solve; :mod:`.race` stops the candidates that have clearly lost.
"""

from rotavg_ros.core.dmf.common import DMFFit, EdgeBlocks, FitSpec, factor_shapes
from rotavg_ros.core.dmf.dense import fit_symmetric
from rotavg_ros.core.dmf.race import CandidateRace
from rotavg_ros.core.dmf.sparse import fit_symmetric_lbfgs
from rotavg_ros.core.dmf.vanilla import fit_vanilla

__all__ = [
    "CandidateRace",
    "DMFFit",
    "EdgeBlocks",
    "FitSpec",
    "factor_shapes",
    "fit_symmetric",
    "fit_symmetric_lbfgs",
    "fit_vanilla",
]
