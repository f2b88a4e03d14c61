"""The settings of one ``genre train`` stage (:class:`TrainConfig`): a named recipe's values, any of them overridden."""

from __future__ import annotations

import dataclasses
import os
from dataclasses import dataclass

from genre_backend.config import INPAINT_HEADS, TARGETS

from .burst import WAYS
from .recipe import STAGES, StageRecipe, documented, get_recipe

__all__ = ["TrainConfig"]


@dataclass
class TrainConfig:
    """Everything one training stage needs; saved beside every checkpoint."""

    stage: str
    data: str | list[str]  # folder(s) of rendered views with targets
    out: str  # run folder; the stage writes OUT/STAGE/
    recipe: str = "paper"  # training/learn/recipe.py: every None below comes from it
    preset: str | None = None  # used only when not starting from --init weights
    init: str | None = None  # weights to start from (the previous stage's best)
    # the recipe's values (StageRecipe: their help texts); None: the named recipe's
    steps: int | None = None
    batch_size: int | None = None
    lr: float | None = None
    beta1: float | None = None
    beta2: float | None = None
    weight_decay: float | None = None
    surface_weight: float | None = None
    photo_fraction: float | None = None
    sph_loss: str | None = None
    depth_weight: float | None = None
    depth_gradient_weight: float | None = None
    depth_offset_weight: float | None = None
    normals_weight: float | None = None
    outline_weight: float | None = None
    lr_halflife: int | None = None
    sph_teacher: float | None = None
    depth_dropout: float | None = None
    mirror: float | None = None
    stretch: float | None = None
    backdrop: float | None = None
    hull_grad_width: float | None = None
    depth_lr_scale: float | None = None
    target: str | None = documented(None, f"the voxel representation to train (GeometryConfig.target: {' or '.join(TARGETS)}); "
                                          "none: the recipe's, else the model's")
    refiner_full_nf: int | None = documented(None, "the width of the refiner's full-resolution branch "
                                                   "(NetworkConfig.refiner_full_nf); none: the recipe's, else the model's")
    inpaint_head: str | None = documented(None, f"the inpainting net's head (NetworkConfig.inpaint_head: {', '.join(INPAINT_HEADS)}); another than the "
                                                "model's gives a fresh inpainting net at the inpaint stage, others refuse it")
    inpaint_widths: str | tuple[int, ...] | None = documented(None, "the inpainting net's four widths, e.g. 32,64,128,256 "
                                                                    "(as --inpaint-head); none: the model's")
    inpaint_from: str | None = documented(None, "weights whose trained inpainting net replaces --init's (a resumed stage: "
                                                "the checkpoint wins)")
    depth_only: str | None = documented(None, "the joint stage: one of --data's folders whose samples train the depth net's "
                                              "own loss alone (the map's and the grid's losses leave them out)")
    true_map: str | None = documented(None, "the joint stage: one of --data's folders whose samples feed the refiner "
                                            "their true full map, the inpainting net's map unscored on them")
    backgrounds: str | None = documented(None, "a 'genre data backgrounds' folder (needed when photo_fraction > 0)")
    val_fraction: float = documented(0.05, "the share of shapes held out for validation")
    val_every: int = documented(200, "validate every this many steps")
    val_samples: int = documented(48, "validation samples each time")
    checkpoint_minutes: float = documented(3.0, "write the resumable checkpoint every this many minutes")
    checkpoint_every: int = documented(0, "also every this many steps (0: off)")
    snapshot_every: int = documented(0, "keep the weights every this many steps in STAGE/snapshots/ (for 'genre train "
                                        "average'; 0: off)")
    log_every: int = documented(10, "a row of log.csv every this many steps")
    seed: int = documented(0, "the seed of the initial weights and of every step's draws (views, augmentation, coins)")
    workers: int = documented(0, "data-loader processes (0: in the training process)")
    device: str = documented("cpu", "the torch device")
    speed: str = documented("auto", "how the nets run: auto (the device's record: channels-last, bf16 autocast where "
                                    "oneDNN has it natively) or one of genre bench train's ways for every net")
    shapes: str | None = None  # optional file with one shape id per line (e.g. the seen-train split)
    augment: bool = True
    progress: bool = True

    def __post_init__(self):
        if self.speed != "auto" and self.speed not in WAYS:
            raise ValueError(f"speed must be 'auto' or one of {', '.join(WAYS)}, got {self.speed!r}")
        if self.stage not in STAGES:
            raise ValueError(f"stage must be one of {STAGES}, got {self.stage!r}")
        recipe = get_recipe(self.recipe)
        if self.preset is None:
            self.preset = recipe.preset
        given = {k: getattr(self, k) for k in StageRecipe.keys() if getattr(self, k) is not None}
        resolved = dataclasses.replace(recipe.stage(self.stage), **given)  # (validates the values)
        for k in StageRecipe.keys():
            setattr(self, k, getattr(resolved, k))
        if self.sph_teacher > 0 and self.stage != "refine":
            raise ValueError(f"sph_teacher: only the refine stage feeds the true map at random (the joint stage: "
                             f"true_map), not {self.stage!r}")
        if self.depth_dropout > 0 and self.stage not in ("refine", "joint"):
            raise ValueError(f"depth_dropout: only the refine and joint stages have depth voxels to empty, not {self.stage!r}")
        if self.stretch > 0 and self.stage != "depth":
            raise ValueError(f"stretch: only the depth stage's samples (picture, depth, mask) can be stretched, not {self.stage!r}'s")
        if self.outline_weight > 0 and self.stage not in ("refine", "joint"):
            raise ValueError(f"outline_weight: only the refine and joint stages train GenRe's grid, not {self.stage!r}")
        if isinstance(self.data, (list, tuple)):
            if not self.data:
                raise ValueError("data: expected at least one views folder")
            self.data = [str(d) for d in self.data]
        for name in ("depth_only", "true_map"):  # a folder of --data whose samples the joint stage treats apart
            folder = getattr(self, name)
            if folder is None:
                continue
            if self.stage != "joint":
                raise ValueError(f"{name}: only the joint stage trains the nets together, not {self.stage!r}")
            folders = [self.data] if isinstance(self.data, str) else self.data
            if os.path.normpath(folder) not in {os.path.normpath(d) for d in folders}:
                raise ValueError(f"{name}: {folder!r} is not one of the --data folders {folders}")
        if self.depth_only is not None and self.depth_weight <= 0:
            raise ValueError("depth_only: its samples train the depth net's own loss alone; set depth_weight > 0")
        if self.depth_only is not None and self.true_map is not None and \
                os.path.normpath(self.depth_only) == os.path.normpath(self.true_map):
            raise ValueError(f"true_map: {self.true_map!r} is the depth_only folder, whose samples feed no refiner")
        if self.target is None:
            self.target = recipe.target
        if self.target is not None and self.target not in TARGETS:
            raise ValueError(f"target: expected one of {TARGETS}, got {self.target!r}")
        if self.refiner_full_nf is None:
            self.refiner_full_nf = recipe.refiner_full_nf
        if self.refiner_full_nf is not None and (isinstance(self.refiner_full_nf, bool) or not isinstance(self.refiner_full_nf, int)
                                                 or self.refiner_full_nf < 0):
            raise ValueError(f"refiner_full_nf: expected an int >= 0, got {self.refiner_full_nf!r}")
        if self.inpaint_head is not None and self.inpaint_head not in INPAINT_HEADS:
            raise ValueError(f"inpaint_head: expected one of {INPAINT_HEADS}, got {self.inpaint_head!r}")
        if self.inpaint_widths is not None:
            given = self.inpaint_widths
            try:
                widths = tuple(int(w) for w in (given.split(",") if isinstance(given, str) else given))
            except (TypeError, ValueError):
                widths = ()
            if len(widths) != 4 or min(widths) < 1:
                raise ValueError(f"inpaint_widths: expected four positive ints (e.g. 32,64,128,256), got {given!r}")
            self.inpaint_widths = widths

    @property
    def learning_rate(self) -> float:
        return self.lr

    def lr_at(self, step: int) -> float:
        """The learning rate of step ``step`` (0-based): ``lr``, halved every ``lr_halflife`` steps when that is set."""
        return self.lr * 0.5 ** (step / self.lr_halflife) if self.lr_halflife else self.lr
