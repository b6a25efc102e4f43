"""The failure monitor: per-step signals of a served call, monitors fitted on labelled rollouts (a probe, the
Mahalanobis distance to successful steps, consecutive-chunk disagreement) with a conformal threshold, the monitor
file, and detection figures over time. Pure NumPy and the standard library, below the side channel: it knows no
model, run or dataset, only arrays.

signals       what one served call gives a monitor (STAC, token entropy, pooled features, sample spread)
scores        fitted scorers and the input basis they share (standardise, impute, project)
monitor_file  `Monitor` (what it scores, its arrays, its threshold), its JSON file, and `EpisodeScore` (live)
fit           fitting from labelled episodes: basis, Ledoit-Wolf, Mahalanobis, the logistic probe, conformal
detection     how early a score finds failed episodes: AUROC over the first N source frames
"""
