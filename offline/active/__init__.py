"""Active learning for the skin predictor: GEN-LAL (a learned selection policy) and the baselines it is measured
against, the benchmark harness and the in-the-loop selection of the poses to simulate next."""
