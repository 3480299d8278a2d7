"""The signal chain: EMG envelopes (:mod:`.emg`), repetitions and their phase (:mod:`.reps`), and the per-phase
N(mu, sigma^2) activation statistics across repetitions (:mod:`.priors`)."""
