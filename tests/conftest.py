"""Suite-wide settings."""
import torch

# The suite's tensors are small: torch's intra-op thread pool only adds spin-waiting on a 2-core
# machine (a 40-step panoptic fit took 3 s on one thread and 66 s on two).
torch.set_num_threads(1)
