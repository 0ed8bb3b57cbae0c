"""The GOV-NeSF network: config, 2D encoder, 3D U-Net, FusionNet, the field and its rendering,
losses, checkpoints, and the averaging baselines; pure tensor ops live in ``mapper.model.ops``."""
