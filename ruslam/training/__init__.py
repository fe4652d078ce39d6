"""Distillation training: Lightning module, data module and the sample augmentations."""
