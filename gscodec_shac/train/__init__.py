"""Optimisation on the CPU: the 3DGS render loss, SHAC-LST fine-tuning and the trainer."""
