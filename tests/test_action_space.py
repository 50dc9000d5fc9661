"""ActionLayout: the B1K preset and one clear error per bad input (docs/design.md §2)."""

import math

import numpy as np
import pytest

from pi0_armfix.action_space import ActionLayout, gripper_boundary

B1K = ActionLayout.preset("b1k_r1pro")


def test_b1k_preset_puts_dim_14_in_left_gripper_and_15_to_22_in_right_arm():
    assert B1K.group_of_dim(14) == "left_gripper"
    assert all(B1K.group_of_dim(d) == "right_arm" for d in range(15, 22))
    assert B1K.groups["right_arm"] == (15, 22)


def test_b1k_preset_covers_23_real_dims_padded_to_32():
    assert (B1K.real_dim, B1K.action_dim) == (23, 32)
    np.testing.assert_array_equal(B1K.grouped_mask(), np.arange(32) < 23)


def test_b1k_preset_marks_the_base_as_a_velocity_group():
    assert B1K.velocity_groups == ("base",)
    np.testing.assert_array_equal(np.flatnonzero(B1K.velocity_mask()), [0, 1, 2])


def test_unknown_velocity_group_is_named():
    _raises(r"velocity_groups names unknown group\(s\) \['wheels'\]",
            lambda: ActionLayout({"base": (0, 3)}, real_dim=3, velocity_groups=("wheels",)))


def test_membership_is_one_hot_on_grouped_dims():
    m = B1K.membership()
    assert m.shape == (32, 6)
    np.testing.assert_array_equal(m.sum(-1), (np.arange(32) < 23).astype(np.float32))


def test_layout_is_hashable_and_equal_by_value():
    assert hash(B1K) == hash(ActionLayout.preset("b1k_r1pro"))
    assert B1K == ActionLayout.preset("b1k_r1pro")


def test_from_config_prefers_explicit_groups():
    layout = ActionLayout.from_config({"preset": "b1k_r1pro", "groups": {"a": (0, 2), "b": (2, 3)},
                                       "real_dim": 3, "action_dim": 4})
    assert layout.group_names == ("a", "b") and layout.action_dim == 4


def _raises(match, fn):
    with pytest.raises(ValueError, match=match):
        fn()


def test_overlapping_groups_name_both_groups():
    _raises(r"group 'right_arm' \(14, 21\) overlaps 'left_gripper' \(14, 15\)", lambda: ActionLayout(
        {"left_gripper": (14, 15), "right_arm": (14, 21)}, real_dim=23))


def test_slice_out_of_range_names_the_group():
    _raises(r"group 'grippers' \(21, 24\) is out of range.*real_dim=23",
            lambda: ActionLayout({"grippers": (21, 24)}, real_dim=23))


def test_negative_start_is_out_of_range():
    _raises(r"group 'base' \(-1, 3\) is out of range", lambda: ActionLayout({"base": (-1, 3)}, 23))


def test_empty_slice_names_the_group():
    _raises(r"group 'torso' \(5, 5\) is an empty slice", lambda: ActionLayout({"torso": (5, 5)}, 23))


def test_real_dim_above_action_dim_names_both():
    _raises(r"layout.real_dim 40 > layout.action_dim 32.*set layout.action_dim and model.action_dim",
            lambda: ActionLayout({"a": (0, 3)}, real_dim=40))


def test_unknown_preset_names_it():
    _raises(r"unknown layout preset 'r2d2'", lambda: ActionLayout.preset("r2d2"))


def test_missing_group_weight_is_an_error_not_a_default():
    _raises(r"group_weights is missing group\(s\) \['right_gripper'\]", lambda: B1K.check_group_weights(
        {g: 1.0 for g in B1K.group_names if g != "right_gripper"}))


def test_unknown_group_weight_key_is_named():
    weights = {g: 1.0 for g in B1K.group_names} | {"grippers": 2.0}
    _raises(r"unknown group\(s\) \['grippers'\]", lambda: B1K.check_group_weights(weights))


def test_negative_group_weight_is_named():
    weights = {g: 1.0 for g in B1K.group_names} | {"left_arm": -3.0}
    _raises(r"group_weights\['left_arm'\] = -3.0 is negative", lambda: B1K.check_group_weights(weights))


def test_nan_group_weight_is_named():
    weights = {g: 1.0 for g in B1K.group_names} | {"base": math.nan}
    _raises(r"group_weights\['base'\] = nan is not finite", lambda: B1K.check_group_weights(weights))


def test_all_zero_group_weights_are_an_error():
    _raises(r"group_weights are all zero", lambda: B1K.check_group_weights(
        {g: 0.0 for g in B1K.group_names}))


def test_dimension_weights_of_wrong_length_name_both_lengths():
    _raises(r"dimension_weights has shape \(23,\); expected \(32,\)",
            lambda: B1K.check_dimension_weights(np.ones(23)))


def test_non_zero_padding_dimension_weight_is_named():
    w = np.r_[np.ones(23), np.zeros(9)]
    w[30] = 0.5
    _raises(r"dimension_weights\[30\] = 0.5 is non-zero on a padding dim",
            lambda: B1K.check_dimension_weights(w))


def test_negative_dimension_weight_is_named():
    w = np.r_[np.ones(23), np.zeros(9)]
    w[3] = -1
    _raises(r"dimension_weights\[3\] = -1.0 is negative", lambda: B1K.check_dimension_weights(w))


def test_all_zero_dimension_weights_are_an_error():
    _raises(r"dimension_weights are all zero", lambda: B1K.check_dimension_weights(np.zeros(32)))


def test_dataset_width_mismatch_names_both_widths():
    _raises(r"my.parquet has action width 21 but the layout's real_dim is 23",
            lambda: B1K.check_real_dim(21, source="my.parquet"))


def test_the_gripper_boundary_separates_open_from_closed_whatever_the_commands_scale():
    # A [-1, 1] command (B1K's grippers) and a [0, 0.1] m finger gap: the midpoint of each range.
    q01, q99 = np.array([-1.0, 0.0]), np.array([1.0, 0.1])
    np.testing.assert_allclose(gripper_boundary(q01, q99), [0.0, 0.05])
    assert gripper_boundary(q01.astype(np.float32), q99.astype(np.float32)).dtype == np.float32
