"""Generation metrics: FRD, FPD, BEV JSD/MMD, TTCE, CTC."""
