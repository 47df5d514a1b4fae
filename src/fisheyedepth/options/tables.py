"""The option tables: each group of options (option name -> kind, :mod:`.kinds`) of the model, the data,
the trainer and the runtimes, checked by :func:`~.kinds.check_options` where the group is read."""

from __future__ import annotations

from .kinds import COUNT, OFFSETS, POSITIVE, SWITCH, WEIGHT, Choice, Either, Group, Kind, ListOf, Number

NET_OPTIONS: dict[str, Kind] = {  # fisheyedepth.models.DepthNet
    "resnet": Number(low=1, whole=True),
    "multi_channel": SWITCH,
    "n_bins": Number(low=2, whole=True),
    "attention": SWITCH,
    "min_distance": POSITIVE,
    "max_distance": POSITIVE,
    "scales": ListOf(Number(0, 4, whole=True, note="the decoder's 5 levels")),
    "base_focal": Number(low=0.0, above=True, optional=True, words=("auto",)),
    "channels_last": SWITCH,
    "decoder_width": Number(0.0, 4.0, above=True, note="a factor on Monodepth2's channels"),
    "cost_volume": Number(low=0, whole=True, note="distance hypotheses; 0: the monocular network"),
    "cost_volume_min": POSITIVE,
    "cost_volume_max": POSITIVE,
    "cost_volume_stride": Number(2, 4, whole=True, note="2 or 4: the encoder map the volume joins"),
    "cost_volume_fusion": Choice(("residual", "replace")),
    "source_dropout": Number(0.0, 1.0),
}
OBJECTIVE_OPTIONS: dict[str, Kind] = {  # fisheyedepth.losses.objective.SelfSupervisedObjective
    "fisheye_projection": SWITCH,
    "real_scale": SWITCH,
    "source_offsets": OFFSETS,
    "rig_offsets": OFFSETS,
    "automask": SWITCH,
    "rim_margin": Number(whole=True, optional=True),  # the objective names a negative margin itself
    "smoothness": WEIGHT,
    "outliers": Number(0.0, 1.0, below=True, note="the fraction of each image's pixels left out"),
    "truth_weight": WEIGHT,
    "photometric_weight": WEIGHT,
    "pose_translation_scale": Number(low=0.0, above=True, optional=True),
}
OPTIMIZER_OPTIONS: dict[str, Kind] = {"lr": POSITIVE, "weight_decay": WEIGHT}
SCHEDULER_OPTIONS: dict[str, Kind] = {
    "step_size": Number(low=1, whole=True),
    "gamma": POSITIVE,
    "T_max": Number(low=1, whole=True),
    "eta_min": WEIGHT,
}
MODEL_OPTIONS: dict[str, Kind] = {  # fisheyedepth.module.FisheyeDepthModule: its groups and its own
    "net": Group(NET_OPTIONS),
    "objective": Group(OBJECTIVE_OPTIONS),
    "optimizer": Group(OPTIMIZER_OPTIONS),
    "scheduler": Group(SCHEDULER_OPTIONS),
    "eval_cap": ListOf(WEIGHT, length=2),
    "log_images_every": COUNT,
    "compile_kernels": SWITCH,
}

# ------------------------------------------------------------------------------------------ the data
AUGMENT_OPTIONS: dict[str, Kind] = {  # fisheyedepth.data.Augment
    "flip": Number(0.0, 1.0, note="a probability"),
    # colour jitter: factors drawn from 1 +- spread, so a spread above 1 could invert the image
    "brightness": Number(0.0, 1.0),
    "contrast": Number(0.0, 1.0),
    "saturation": Number(0.0, 1.0),
    "hue": Number(0.0, 0.5, note="turns of the chroma plane"),
}
POSE_NOISE_OPTIONS: dict[str, Kind] = {  # fisheyedepth.data.PoseNoise
    "rotation_deg": WEIGHT,
    "translation": WEIGHT,
    "seed": Number(whole=True),
}
DATAMODULE_OPTIONS: dict[str, Kind] = {  # fisheyedepth.data.FisheyeDataModule
    "offsets": OFFSETS,
    "rig_offsets": OFFSETS,
    "min_translation": WEIGHT,
    "max_translation": POSITIVE,
    "augment": Group(AUGMENT_OPTIONS, optional=True),
    "skip_bad_frames": SWITCH,
    "batch_size": Number(low=1, whole=True),
    "num_workers": COUNT,
    "pin_memory": SWITCH,
    "seed": Number(whole=True),
    "pose_noise": Group(POSE_NOISE_OPTIONS, optional=True),
    "lidar_occlusion": Number(low=0.0, optional=True),
    "source_baseline": Number(low=0.0, above=True, optional=True),
    "max_pose_gap": Number(low=0.0, above=True, optional=True),
}

# ------------------------------------------------------------------------------------------ the trainer
# Lightning's precisions (trainer.precision; auto: fisheyedepth.config.resolve_precision)
TRAINING_PRECISIONS = ("auto", "32-true", "32", "bf16-mixed", "bf16-true", "bf16", "16-mixed", "16-true")
TRAINING_PRECISIONS += ("16", "64-true", "64", "transformer-engine", "transformer-engine-float16")
ACCELERATORS = ("auto", "cpu", "cuda", "gpu", "mps")  # auto: CUDA where torch sees a GPU, else the CPU
BATCHES = Either(  # Lightning's limit_*_batches and val_check_interval: a fraction, or a count
    (Number(0.0, 1.0, above=True), Number(low=1, whole=True)),
    "a fraction in (0, 1] or a whole number of batches >= 1",
)
TRAINER_OPTIONS: dict[str, Kind] = {  # lightning.Trainer, as conf/trainer sets it
    "max_epochs": Number(low=1, whole=True, note="-1 would train without end, 0 not at all"),
    "max_steps": Number(low=1, whole=True, also=(-1,), note="-1: no limit but max_epochs"),
    "limit_train_batches": BATCHES,
    "limit_val_batches": Either(
        (BATCHES, Number(0, 0, whole=True)),
        "a fraction in (0, 1] or a whole number of batches >= 0 (0: no validation)",
    ),
    "val_check_interval": Either(
        (Number(0.0, 1.0, above=True, optional=True), Number(low=1, whole=True)), BATCHES.what
    ),
    "check_val_every_n_epoch": Number(low=1, whole=True, optional=True),
    "num_sanity_val_steps": Number(low=-1, whole=True, note="-1: every validation batch"),
    "accumulate_grad_batches": Number(low=1, whole=True),
    "gradient_clip_val": Number(low=0.0, optional=True, note="null or 0: no clipping"),
    "gradient_clip_algorithm": Choice(("norm", "value"), optional=True),
    "log_every_n_steps": Number(low=1, whole=True),
    "precision": Choice(TRAINING_PRECISIONS),
    "accelerator": Choice(ACCELERATORS),
    "devices": Either(
        (Number(low=1, whole=True, also=(-1,), words=("auto",)), ListOf(Number(low=0, whole=True))),
        "a whole number >= 1, -1 (every device), auto or a list of device numbers",
    ),
    "num_nodes": Number(low=1, whole=True),
    "sync_batchnorm": SWITCH,
    "deterministic": Either((SWITCH, Choice(("warn",))), "true, false or warn"),
    "fast_dev_run": Either(
        (SWITCH, Number(low=1, whole=True)), "a boolean or a whole number of batches >= 1"
    ),
    "enable_progress_bar": SWITCH,
}

RUNTIME_PRECISIONS = ("fp32", "bf16")  # what predict, eval and export run in
POST_PROCESSING = ("none", "flip")  # what a runtime does with the network's distance (see flip_averaged)
