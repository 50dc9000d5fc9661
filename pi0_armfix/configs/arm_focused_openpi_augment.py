"""`arm_focused` with openpi's geometric augmentation on the head camera
(`model.augment.crop_scale=0.95`, `model.augment.rotate_degrees=5`; the colour jitter as the main
job has it): the comparison behind the demo's default of no geometric augmentation. On the demo's
32 px head camera a 95 % crop or a 5 degree turn moves the target by about a pixel, which is ~5 cm
of distance, while the arrival radius is 6 cm.

  python -m pi0_armfix.train --config=configs/arm_focused_openpi_augment.py
"""

from pi0_armfix.configs import arm_focused


def get_config(arg=None):
    config = arm_focused.get_config(arg)
    config.model.augment.crop_scale = 0.95
    config.model.augment.rotate_degrees = 5.0
    return config
