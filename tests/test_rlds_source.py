"""RLDS source on a tiny array_record dataset that the test builds with TFDS (no TensorFlow)."""

import pickle

import numpy as np
import pytest
import tensorflow_datasets as tfds
from ml_collections import ConfigDict
from PIL import Image

from data_fixtures import frame_colour
from pi0_armfix.action_space import ActionLayout
from pi0_armfix.data.formats.rlds import RldsSource
from pi0_armfix.data.formats.sources import open_source

LAYOUT = ActionLayout.preset("b1k_r1pro")
LENGTHS = (5, 8, 6)
CAMERAS = ("rgb_head", "rgb_left_wrist", "rgb_right_wrist")


def _episode(e: int) -> dict:
    """Episode e: actions/state filled with e*100 + step, a uniform frame_colour image per camera."""
    n = LENGTHS[e]
    steps = []
    for i in range(n):
        observation = {"state": np.full(23, e * 100 + i, np.float32)}
        for c, camera in enumerate(CAMERAS):
            image = np.broadcast_to(frame_colour(e, i, c), (8, 8, 3)).copy()
            observation[camera] = Image.fromarray(image)  # TFDS encodes PIL images without TF
        steps.append({"observation": observation,
                      "action": np.full(23, e * 100 + i + 0.5, np.float32),
                      "language_instruction": f"task {e}", "is_first": i == 0})
    return {"steps": steps}


class Pi0ArmfixTinyRlds(tfds.core.GeneratorBasedBuilder):
    """Three RLDS episodes of B1K-shaped steps."""

    VERSION = tfds.core.Version("1.0.0")

    def _info(self):
        image = tfds.features.Image(shape=(8, 8, 3), encoding_format="png")
        return tfds.core.DatasetInfo(builder=self, features=tfds.features.FeaturesDict({
            "steps": tfds.features.Dataset({
                "observation": tfds.features.FeaturesDict(
                    {"state": tfds.features.Tensor(shape=(23,), dtype=np.float32),
                     **{camera: image for camera in CAMERAS}}),
                "action": tfds.features.Tensor(shape=(23,), dtype=np.float32),
                "language_instruction": tfds.features.Text(),
                "is_first": np.bool_,
            })}))

    def _split_generators(self, dl_manager):
        return {"train": self._generate_examples()}

    def _generate_examples(self):
        for e in range(len(LENGTHS)):
            yield e, _episode(e)


@pytest.fixture(scope="module")
def rlds_root(tmp_path_factory):
    builder = Pi0ArmfixTinyRlds(data_dir=str(tmp_path_factory.mktemp("tfds")),
                                file_format="array_record")
    builder.download_and_prepare()
    return builder.data_dir


def test_reads_steps_as_frames(rlds_root):
    source = RldsSource(rlds_root, LAYOUT)
    table = source.load_table()

    assert source.num_episodes == 3 and list(source.tasks) == ["task 0", "task 1", "task 2"]
    np.testing.assert_array_equal(source.episode_lengths, LENGTHS)
    expected = np.concatenate([e * 100 + np.arange(n) for e, n in enumerate(LENGTHS)])
    np.testing.assert_array_equal(table.actions, np.repeat(expected[:, None] + 0.5, 23, 1))
    np.testing.assert_array_equal(table.state, np.repeat(expected[:, None], 23, 1))
    np.testing.assert_array_equal(table.episode_starts, [0, 5, 13, 19])


def test_iter_blocks_yields_one_episode_per_block_in_the_order_given(rlds_root):
    blocks = list(RldsSource(rlds_root, LAYOUT).iter_blocks(("actions",), episodes=[2, 0]))
    assert [b["episode_index"].tolist() for b in blocks] == [[2] * 6, [0] * 5]
    np.testing.assert_array_equal(blocks[0]["actions"][:, 0], 200 + np.arange(6) + 0.5)


def test_decodes_images_of_the_chosen_episodes(rlds_root):
    source = RldsSource(rlds_root, LAYOUT)
    assert source.cameras == {"base_0_rgb": "observation/rgb_head",
                              "left_wrist_0_rgb": "observation/rgb_left_wrist",
                              "right_wrist_0_rgb": "observation/rgb_right_wrist"}
    table = source.load_table([2, 1])
    images = pickle.loads(pickle.dumps(table.images))  # as a worker process gets it
    for frame in (7, 0, 10, 3):  # episode 1 step 1, episode 2 step 0, ...
        position = int(table.episode_of_frame(np.array([frame]))[0])
        episode, step = int(table.episode_index[position]), frame - table.episode_starts[position]
        for c, camera in enumerate(table.images.cameras):
            np.testing.assert_array_equal(images(frame)[camera][0, 0], frame_colour(episode, step, c))


def test_open_source_reads_rlds(rlds_root):
    source = open_source(ConfigDict({"root": str(rlds_root), "format": "rlds"}), LAYOUT)
    assert isinstance(source, RldsSource) and source.num_episodes == 3


def test_action_width_different_from_the_layout_is_an_error(rlds_root):
    layout = ActionLayout(groups={"arm": (0, 7)}, real_dim=7)
    with pytest.raises(ValueError, match=r"steps/action'\) has action width 23 but the layout's "
                                         r"real_dim is 7"):
        RldsSource(rlds_root, layout)


def test_a_folder_without_dataset_info_is_an_error(tmp_path):
    with pytest.raises(ValueError, match=r"not a TFDS dataset directory: .*dataset_info.json"):
        RldsSource(tmp_path, LAYOUT)


def test_an_unknown_split_is_an_error(rlds_root):
    with pytest.raises(ValueError, match=r"has no split 'validation'; splits: \['train'\]"):
        RldsSource(rlds_root, LAYOUT, split="validation")


def test_episode_out_of_range_is_an_error(rlds_root):
    with pytest.raises(ValueError, match=r"episode 3 is out of range: .* has 3 episodes"):
        RldsSource(rlds_root, LAYOUT).load_table([3])
