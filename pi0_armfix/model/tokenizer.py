"""Prompt tokenizer: a sentencepiece model, used the way openpi's PaligemmaTokenizer uses it.

`tokenizer(prompt, state=None) -> (tokens int32 [max_token_len], mask bool [max_token_len])`:
the prompt is stripped and "_" and "\\n" become spaces. pi0 (no state): it is encoded with BOS,
then "\\n" (the start-of-answer token) is encoded and appended. pi0.5 (`state_in_prompt`; the
state given, normalized, real dims only): the state is digitized into 256 bins over [-1, 1]
(`np.digitize(state, linspace(-1, 1, 257)[:-1]) - 1`, as openpi) and the text
`"Task: {prompt}, State: {b_0} {b_1} ...;\\nAction: "` is encoded with BOS. The result is
right-padded with 0 (mask False) or truncated to max_token_len.

Which sentencepiece model (`make_tokenizer(config.model, prompts=...)`):
  * `model.tokenizer` set: that file (PaliGemma's `paligemma_tokenizer.model` for real runs;
    required with `model.pretrained`, whose embedding rows are PaliGemma's token ids);
  * empty: a small BPE model trained offline on the dataset's prompts with
    `sentencepiece.SentencePieceTrainer` (deterministic; cached under `cache_root()` by a hash of the
    prompts and the vocabulary size, which never exceeds the preset's `vocab_size`).
Training builds it once and passes it to the data pipeline, which applies it before batching.
"""

from __future__ import annotations

import hashlib
import io
import os
import pathlib
from collections.abc import Iterable, Mapping
from typing import Any

import numpy as np
import sentencepiece

from pi0_armfix.cache import cache_root
from pi0_armfix.model.config import from_model_config

# PaliGemma's special ids: pad 0 (also the padding token of tokenized prompts), eos 1, bos 2, unk 3.
_SPECIAL_IDS = dict(pad_id=0, eos_id=1, bos_id=2, unk_id=3)


def clean_prompt(prompt: str) -> str:
    return prompt.strip().replace("_", " ").replace("\n", " ")


def state_bins(state: np.ndarray) -> np.ndarray:
    """Normalized state [S] -> its 256-bin indices over [-1, 1] (openpi's discretization)."""
    return np.digitize(np.asarray(state), bins=np.linspace(-1, 1, 256 + 1)[:-1]) - 1


def pi05_prompt(prompt: str, state: np.ndarray) -> str:
    """openpi's pi0.5 prompt text with the state written in."""
    return f"Task: {clean_prompt(prompt)}, State: {' '.join(map(str, state_bins(state)))};\nAction: "


class Tokenizer:
    """`tokenizer(prompt, state=None) -> (tokens int32 [max_len], mask bool [max_len])`."""

    def __init__(self, model_proto: bytes, max_len: int, *, vocab_size: int, source: str,
                 state_in_prompt: bool = False):
        """Args:
          model_proto: serialized sentencepiece model.
          max_len: output length L.
          vocab_size: the model's embedding rows; a larger sentencepiece vocabulary is an error.
          source: where the model came from, for error messages.
          state_in_prompt: pi0.5: the data pipeline passes each sample's normalized state.
        """
        self.state_in_prompt = state_in_prompt
        self.model_proto = model_proto
        self._processor = sentencepiece.SentencePieceProcessor(model_proto=model_proto)
        if self._processor.vocab_size() > vocab_size:
            raise ValueError(f"tokenizer {source} has {self._processor.vocab_size()} pieces but "
                             f"the model preset embeds only vocab_size={vocab_size} tokens")
        self.max_len = max_len
        self.vocab_size = self._processor.vocab_size()

    def __call__(self, prompt: str, state: np.ndarray | None = None) -> tuple[np.ndarray, np.ndarray]:
        if state is None:
            tokens = (self._processor.encode(clean_prompt(prompt), add_bos=True)
                      + self._processor.encode("\n"))
        else:
            tokens = self._processor.encode(pi05_prompt(prompt, state), add_bos=True)
        tokens = tokens[: self.max_len]
        mask = np.zeros((self.max_len,), bool)
        mask[: len(tokens)] = True
        padded = np.zeros((self.max_len,), np.int32)
        padded[: len(tokens)] = tokens
        return padded, mask

    def decode(self, tokens: np.ndarray, mask: np.ndarray) -> str:
        return self._processor.decode([int(t) for t in np.asarray(tokens)[np.asarray(mask)]])


def training_corpus(prompts: Iterable[str], state_in_prompt: bool) -> list[str]:
    """The texts the offline tokenizer learns: the cleaned prompts; for pi0.5 each in its prompt
    format with every state bin (-1 .. 255) written once, so numbers get pieces of their own."""
    corpus = sorted({clean_prompt(p) for p in prompts} - {""})
    if state_in_prompt:
        every_bin = np.r_[-2.0, -1 + (np.arange(256) + 0.5) / 128]  # bins -1 (below -1) .. 255
        corpus = [pi05_prompt(p, every_bin) for p in corpus]
    return corpus


def train_sentencepiece(corpus: Iterable[str], vocab_size: int) -> bytes:
    """A small BPE sentencepiece model of the texts, at most `vocab_size` pieces.

    BPE (not unigram) because on a few dozen prompts it still merges up to whole words, keeping
    prompts short; unseen words fall back to characters.

    Normalization is the identity and "\\n" is a piece of its own, as in PaliGemma's tokenizer.
    """
    corpus = sorted(set(corpus))
    if not corpus:
        raise ValueError("cannot build the offline tokenizer: no non-empty prompts were given")
    model = io.BytesIO()
    sentencepiece.SentencePieceTrainer.train(
        sentence_iterator=iter(corpus), model_writer=model, vocab_size=vocab_size,
        hard_vocab_limit=False, model_type="bpe", character_coverage=1.0,
        normalization_rule_name="identity", add_dummy_prefix=False, user_defined_symbols=["\n"],
        num_threads=1, minloglevel=2, **_SPECIAL_IDS)
    return model.getvalue()


def cached_sentencepiece(prompts: Iterable[str], vocab_size: int,
                         cache_dir: str | os.PathLike | None = None, *,
                         state_in_prompt: bool = False) -> pathlib.Path:
    """Path of the offline model for these prompts, trained on first use (atomic write)."""
    corpus = training_corpus(prompts, state_in_prompt)
    digest = hashlib.sha256("\0".join([str(vocab_size), *corpus]).encode()).hexdigest()[:16]
    path = cache_root(cache_dir) / "tokenizers" / f"spm_{vocab_size}_{digest}.model"
    if not path.exists():
        path.parent.mkdir(parents=True, exist_ok=True)
        tmp = path.with_suffix(f".tmp{os.getpid()}")
        tmp.write_bytes(train_sentencepiece(corpus, vocab_size))
        os.replace(tmp, path)
    return path


def make_tokenizer(model_cfg: Mapping[str, Any], *, prompts: Iterable[str] | None = None,
                   cache_dir: str | os.PathLike | None = None) -> Tokenizer:
    """The tokenizer for the `model` config section (`preset`, `tokenizer`, `pretrained`).

    Args:
      model_cfg: `config.model`.
      prompts: every task prompt of the dataset; needed when `model.tokenizer` is empty.
      cache_dir: where the offline model is cached (default: see `cache_root`).
    """
    config = from_model_config(model_cfg)
    path = model_cfg.get("tokenizer") or ""
    if path:
        path = pathlib.Path(path).expanduser()
        if not path.is_file():
            raise ValueError(f"model.tokenizer = {str(path)!r} is not a file (a sentencepiece .model)")
        return Tokenizer(path.read_bytes(), config.max_token_len, vocab_size=config.vocab_size,
                         source=f"model.tokenizer={str(path)!r}", state_in_prompt=config.pi05)
    if model_cfg.get("pretrained"):
        raise ValueError("model.pretrained is set but model.tokenizer is empty: pretrained weights need "
                         "the tokenizer they were trained with (PaliGemma's paligemma_tokenizer.model)")
    if prompts is None:
        raise ValueError("model.tokenizer is empty: pass the dataset's prompts to build the "
                         "offline tokenizer")
    path = cached_sentencepiece(prompts, config.vocab_size, cache_dir, state_in_prompt=config.pi05)
    return Tokenizer(path.read_bytes(), config.max_token_len, vocab_size=config.vocab_size,
                     source=f"{str(path)!r} (offline, from the dataset prompts)",
                     state_in_prompt=config.pi05)
