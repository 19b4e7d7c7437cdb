"""``rsmb bench`` and the tools it measures with: the benchmark sections, the ECC/ORB/DIS
baselines and the synthetic survey archive builder."""
