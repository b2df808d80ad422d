"""The standard evaluation of shape models (Bernard et al., CVPR 2016, section 3.1), in three
parts as scikit-learn separates metrics from model selection and from displays:

- :mod:`core.evaluation.measures`: reconstruction, generalisation, specificity, sparse
  reconstruction and compactness of a fitted model (functions of a model and shapes);
- :mod:`core.evaluation.protocol`: which model is fitted on which shapes -- the full model, the
  leave-one-out folds (fixed, or true leave-one-out re-aligning and re-corresponding each
  fold), the sparse fit's noise -- in a cancellable process pool;
- :mod:`core.evaluation.plotting`: the summary table, JSON, and the paper's Figure 4 boxplots.
"""

from core.evaluation.measures import (
    compactness,
    reconstruction_errors,
    residual_variance,
    sparse_fit,
    specificity,
    vertex_errors,
)
from core.evaluation.plotting import (
    LABELS,
    PER_SHAPE_MEASURES,
    plot_metrics,
    summary_rows,
    summary_table,
    to_json,
)
from core.evaluation.protocol import (
    LEAVE_ONE_OUT,
    MEASURES,
    Realign,
    Recorrespond,
    evaluate_methods,
    evaluate_model,
)
from core.runtime.progress import Cancelled

__all__ = ["MEASURES", "LEAVE_ONE_OUT", "LABELS", "PER_SHAPE_MEASURES", "evaluate_model",
           "evaluate_methods", "Realign", "Recorrespond", "vertex_errors",
           "reconstruction_errors", "residual_variance", "sparse_fit", "compactness",
           "specificity", "summary_rows", "summary_table", "to_json", "plot_metrics",
           "Cancelled"]
