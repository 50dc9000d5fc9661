"""What makes two starts on one run folder the same run (pi0_armfix.training.fingerprint)."""

from pi0_armfix.training import fingerprint


def test_fingerprint_keys_are_what_gives_the_saved_state_its_meaning():
    for key in ("seed", "model.preset", "loss.group_weights.left_arm", "layout.preset",
                "data.root", "data.curriculum", "train.batch_size"):
        assert fingerprint.is_fingerprint_key(key), key
    for key in ("optim.lr", "train.total_steps", "eval.every", "data.num_workers",
                "model.pretrained", "sharding.fsdp"):
        assert not fingerprint.is_fingerprint_key(key), key


def test_a_relative_and_an_absolute_data_root_of_one_folder_are_the_same_run(tmp_path,
                                                                            monkeypatch):
    monkeypatch.chdir(tmp_path)
    changed, _ = fingerprint.differences({"data": {"root": "demo"}},
                                         {"data": {"root": str(tmp_path / "demo")}})
    assert changed == []


def test_a_run_saved_before_a_key_existed_compares_as_if_it_held_the_keys_default():
    saved = {"data": {"root": "/d"}}  # a config.json written before data.video_access existed
    current = {"data": {"root": "/d", "video_access": "auto", "stream_episodes": 16,
                        "stream_shuffle": 256}}
    assert fingerprint.differences(saved, current) == ([], [])
    changed, _ = fingerprint.differences(saved, {"data": {"root": "/d", "video_access": "stream"}})
    assert changed == ["data.video_access: 'auto' -> 'stream'"]
