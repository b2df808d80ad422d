"""Local-support deformation factors (Bernard et al., CVPR 2016), in four parts:

- :mod:`~core.models.lsf.graph`: the weighted graph gradient E of the smoothness term;
- :mod:`~core.models.lsf.prox`: proximal operators of the factor norm (l1, l1/l-inf or l1/l2
  vertex groups, l2, graph term);
- :mod:`~core.models.lsf.solver`: block coordinate descent on the factorisation (Eq. 5);
- :mod:`~core.models.lsf.splitting`: factor splitting by connected support regions;
- :mod:`~core.models.lsf.estimator`: the :class:`LSF` estimator.
"""

from core.models.lsf.estimator import LSF, drop_unexplaining
from core.models.lsf.graph import graph_gradient, spectral_norm_sq
from core.models.lsf.prox import GROUP_NORMS, FactorNorm, project_l1_ball, prox_group, prox_sparse_group
from core.models.lsf.solver import structured_factorisation
from core.models.lsf.splitting import split_factors

__all__ = ["LSF", "FactorNorm", "GROUP_NORMS", "graph_gradient", "spectral_norm_sq",
           "project_l1_ball", "prox_group", "prox_sparse_group", "structured_factorisation",
           "split_factors", "drop_unexplaining"]
