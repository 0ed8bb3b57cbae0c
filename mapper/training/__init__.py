"""Training and evaluation: data, the training loop, evaluation, metrics and their CLIs.
"""
