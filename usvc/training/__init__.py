"""Scene coordinate head training: augmentation, reprojection loss and its threshold schedule."""

from usvc.training.augment import AugmentedView, augment, resized_shape, roll_rotation, warp_view
from usvc.training.reprojection_loss import reprojection_loss
from usvc.training.schedule import circle_threshold

__all__ = [
    "AugmentedView",
    "augment",
    "circle_threshold",
    "reprojection_loss",
    "resized_shape",
    "roll_rotation",
    "warp_view",
]
