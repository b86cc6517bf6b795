"""The arm experiment's statistics ([AX-7]): the shared module :mod:`softrtc.paired_stats` under its arm name.

The arm report and the Kinetix study table ([KR-3]) use the same bootstrap,
paired tests and Holm adjustment; they live in :mod:`softrtc.paired_stats`.
"""

from softrtc.paired_stats import (EXACT_SIGN_FLIP, as_matrix, cluster_bootstrap, holm, mcnemar_exact,  # noqa: F401
                                  paired_difference, sign_flip_test)

__all__ = ["cluster_bootstrap", "paired_difference", "mcnemar_exact", "sign_flip_test", "holm", "as_matrix"]
