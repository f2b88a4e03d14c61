"""The settings of one ``genre train`` stage (:class:`TrainConfig`): a named recipe's values, any of them overridden."""

from __future__ import annotations

import dataclasses
from dataclasses import dataclass

from genre_backend.config import INPAINT_HEADS, TARGETS

from .burst import WAYS
from .recipe import STAGES, StageRecipe, get_recipe

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
    steps: int | None = None
    batch_size: int | None = None  # per process
    lr: float | None = None
    beta1: float | None = None
    beta2: float | None = None
    surface_weight: float | None = None
    photo_fraction: float | None = None
    sph_loss: str | None = None
    depth_weight: float | None = None
    depth_gradient_weight: float | None = None  # depth, joint: the depth error's gradient matching term's weight
    outline_weight: float | None = None  # refine, joint: the silhouettes' term's weight (losses.outline_loss)
    lr_halflife: int | None = None
    sph_teacher: float | None = None  # refine: the share of samples fed the true full map (teacher forcing)
    depth_dropout: float | None = None  # refine, joint: the share of samples whose depth voxels are emptied
    mirror: float | None = None  # every stage: the share of training samples reflected left to right
    target: str | None = None  # the voxel representation to train (GeometryConfig.target); None: the recipe's, else the model's
    refiner_full_nf: int | None = None  # the refiner's full-resolution branch (NetworkConfig.refiner_full_nf); None: the recipe's, else the model's
    # the inpainting net's head (NetworkConfig.inpaint_head) and its four widths ("32,64,128,256";
    # NetworkConfig.inpaint_widths); None: the model's.  Another head or other widths than the model's give a
    # fresh inpainting net at the inpaint stage (nets.model.with_inpaint_net); other stages refuse them.
    inpaint_head: str | None = None
    inpaint_widths: str | tuple[int, ...] | None = None
    # weights whose trained inpainting net replaces --init's (nets.model.with_inpaint_net_of), e.g. a wider net
    # trained in another run put under later weights' depth net and refiner (a resumed stage: the checkpoint wins, as for --init)
    inpaint_from: str | None = None
    backgrounds: str | None = None  # a 'genre data backgrounds' folder (needed when photo_fraction > 0)
    val_fraction: float = 0.05
    val_every: int = 200
    val_samples: int = 48
    checkpoint_minutes: float = 3.0
    checkpoint_every: int = 0  # also every this many steps (0: off)
    snapshot_every: int = 0  # keep the weights every this many steps in STAGE/snapshots/ (for 'genre train average'; 0: off)
    log_every: int = 10
    seed: int = 0
    workers: int = 0
    device: str = "cpu"
    # how the nets run: "auto" (the device's record, burst.Speed.for_device: on a CPU channels-last, with bf16
    # autocast where oneDNN has it natively) or one of genre bench train's ways for every net (burst.WAYS)
    speed: str = "auto"
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
            raise ValueError(f"sph_teacher: only the refine stage feeds the true map, not {self.stage!r}")
        if self.depth_dropout > 0 and self.stage not in ("refine", "joint"):
            raise ValueError(f"depth_dropout: only the refine and joint stages have depth voxels to empty, not {self.stage!r}")
        if self.outline_weight > 0 and self.stage not in ("refine", "joint"):
            raise ValueError(f"outline_weight: only the refine and joint stages train GenRe's grid, not {self.stage!r}")
        if isinstance(self.data, (list, tuple)):
            if not self.data:
                raise ValueError("data: expected at least one views folder")
            self.data = [str(d) for d in self.data]
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
