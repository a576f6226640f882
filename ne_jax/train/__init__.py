"""Training: ray batches, losses, the train state, the jitted step and checkpoints."""

from ne_jax.train.checkpoint import (
    CheckpointError,
    CheckpointNotFoundError,
    latest_checkpoint,
    load_checkpoint,
    save_checkpoint,
)
from ne_jax.train.losses import (
    TERMS,
    LossConfig,
    confidence_loss,
    loss_terms,
    normal_loss,
    normal_mismatch,
    orientation_loss,
    photometric_loss,
    sparsity_loss,
    total_loss,
)
from ne_jax.train.sampler import (
    Batch,
    RayPool,
    SamplerConfig,
    band_mask,
    build_pool,
    pixel_index_rays,
    sample_batch,
)
from ne_jax.train.state import TrainConfig, TrainState, init_train_state
from ne_jax.train.step import make_train_step

__all__ = [
    "TERMS",
    "Batch",
    "CheckpointError",
    "CheckpointNotFoundError",
    "LossConfig",
    "RayPool",
    "SamplerConfig",
    "TrainConfig",
    "TrainState",
    "band_mask",
    "build_pool",
    "confidence_loss",
    "init_train_state",
    "latest_checkpoint",
    "load_checkpoint",
    "loss_terms",
    "make_train_step",
    "normal_loss",
    "normal_mismatch",
    "orientation_loss",
    "photometric_loss",
    "pixel_index_rays",
    "sample_batch",
    "save_checkpoint",
    "sparsity_loss",
    "total_loss",
]
