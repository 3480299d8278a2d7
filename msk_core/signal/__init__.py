"""The signal layer: EMG envelopes with their quality and fatigue, device clocks, repetitions and their phase
(:mod:`.reps`: the one segmenter, offline, live and of a phase stream), gait cycles and the coordinates' filter. The
per-phase N(mu, sigma^2) activation prior fitted across repetitions is the estimator's: :mod:`msk_core.estimate.prior`.
"""
