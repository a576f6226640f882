"""Training: the run config and its presets, ray batches, losses, the train state, the jitted step,
checkpoints, the training run and the trained model it returns."""

from ne_jax.train.checkpoint import (
    CheckpointError,
    CheckpointNotFoundError,
    latest_checkpoint,
    load_checkpoint,
    save_checkpoint,
)
from ne_jax.train.loop import StartFrom, TrainingDiverged, train
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
from ne_jax.train.model import TrainedModel, load_trained, save_trained
from ne_jax.train.run import InitConfig, RunConfig, get_run_preset, load_run_config
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
    "InitConfig",
    "RunConfig",
    "StartFrom",
    "TrainedModel",
    "TrainingDiverged",
    "get_run_preset",
    "load_run_config",
    "load_trained",
    "save_trained",
    "train",
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
