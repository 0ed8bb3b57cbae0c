"""CLIP's byte-level BPE tokenizer, read from a local ``bpe_simple_vocab_16e6.txt.gz``.

A faithful re-implementation of OpenAI CLIP's ``simple_tokenizer.py`` (the same algorithm
open_clip ships), so token ids match the ones the released CLIP text towers were trained on:

1. clean the text: ``ftfy.fix_text`` when ftfy is installed (optional; without it only the
   steps below run, which is identical for plain ASCII/UTF-8 prompts), Unicode NFC normalisation
   (what ``ftfy.fix_text`` does last, so a decomposed "cafe\\u0301" tokenises as "café" with or
   without ftfy), HTML-unescape twice, collapse whitespace, lower-case;
2. split with CLIP's regex (contractions, runs of letters, single digits, runs of punctuation);
3. map every UTF-8 byte of a piece to a printable unicode character (``bytes_to_unicode``),
   mark the end of the word with ``</w>`` and apply the BPE merges in rank order;
4. look the merged symbols up in the vocabulary: 256 byte symbols, the same 256 with ``</w>``,
   one symbol per merge, then ``<|startoftext|>`` and ``<|endoftext|>``.

``tokenize`` wraps each text as ``[SOT] tokens [EOT]``, pads with 0 to the context length and,
like open_clip, truncates over-long texts to the context length keeping EOT as the last token.

The merges file format: a header line (``#version: 0.2``), then one merge a line, two symbols
separated by one space (``t h``, ``th e</w>``). Only the first ``max_merges`` merges are used
(48894 for the released CLIP models, which gives their 49408-token vocabulary).

Example (with a tiny merges file)::

    >>> import gzip, os, tempfile
    >>> path = os.path.join(tempfile.mkdtemp(), "bpe.txt.gz")
    >>> with gzip.open(path, "wt", encoding="utf-8") as f:
    ...     _ = f.write("#version: 0.2\\nt h\\nth e</w>\\n")
    >>> tok = ClipTokenizer(path, context_length=6)
    >>> tok.encode("The")  # one merged symbol: 'the</w>'
    [513]
    >>> tok.decode(tok.encode("The  the"))
    'the the '
    >>> tok.tokenize(["the"]).tolist()
    [[514, 513, 515, 0, 0, 0]]
"""

from __future__ import annotations

import gzip
import html
import unicodedata
from collections.abc import Sequence
from functools import lru_cache
from pathlib import Path

import numpy as np

from govnesf._extras import require

regex = require("regex", "clip", "the CLIP tokenizer")

#: Merges the released CLIP models use: 49152 - 256 - 2 (vocabulary 49408 = 2 * 256 + 48894 + 2).
CLIP_MAX_MERGES = 49152 - 256 - 2

SOT_TEXT = "<|startoftext|>"
EOT_TEXT = "<|endoftext|>"

_PATTERN = regex.compile(
    r"""<\|startoftext\|>|<\|endoftext\|>|'s|'t|'re|'ve|'m|'ll|'d|[\p{L}]+|[\p{N}]|[^\s\p{L}\p{N}]+""",
    regex.IGNORECASE,
)
_WHITESPACE = regex.compile(r"\s+")


@lru_cache
def bytes_to_unicode() -> dict[int, str]:
    """Byte value (0..255) -> a printable unicode character, a bijection (CLIP's / GPT-2's table).

    Printable Latin-1 bytes map to themselves; the others map to code points 256 and up, so the
    BPE never sees whitespace or control characters.
    """
    bs = list(range(ord("!"), ord("~") + 1)) + list(range(ord("¡"), ord("¬") + 1))
    bs += list(range(ord("®"), ord("ÿ") + 1))
    cs = bs[:]
    n = 0
    for b in range(256):
        if b not in bs:
            bs.append(b)
            cs.append(256 + n)
            n += 1
    return dict(zip(bs, (chr(c) for c in cs), strict=True))


def _pairs(word: tuple[str, ...]) -> set[tuple[str, str]]:
    """Adjacent symbol pairs of a word."""
    return set(zip(word[:-1], word[1:], strict=True))


def clean_text(text: str) -> str:
    """CLIP's text cleanup: ftfy (if installed), NFC, HTML unescape x2, whitespace collapsed, lower case."""
    try:
        import ftfy  # optional
    except ImportError:  # pragma: no cover - depends on the environment
        ftfy = None
    if ftfy is not None:  # pragma: no cover - ftfy is not installed in CI
        text = ftfy.fix_text(text)
    text = unicodedata.normalize("NFC", text)  # ftfy's last step; composed and decomposed text agree
    text = html.unescape(html.unescape(text)).strip()
    return _WHITESPACE.sub(" ", text).strip().lower()


class ClipTokenizer:
    """CLIP's byte-level BPE tokenizer.

    Args:
        bpe_path: local ``bpe_simple_vocab_16e6.txt.gz`` (gzip, or plain text if the name does not
            end in ``.gz``).
        context_length: tokens a row of :meth:`tokenize` holds (77 for the released models).
        max_merges: use only the first ``max_merges`` merges of the file.

    Raises:
        FileNotFoundError: ``bpe_path`` does not exist.
        ValueError: the file is not a merges file (a line that is not two symbols), or an argument
            is out of range.
    """

    def __init__(
        self, bpe_path: str | Path, context_length: int = 77, max_merges: int = CLIP_MAX_MERGES
    ) -> None:
        if not isinstance(context_length, int) or context_length < 2:
            raise ValueError(f"context_length {context_length!r} out of range: need an int >= 2 (SOT + EOT)")
        if not isinstance(max_merges, int) or max_merges < 0:
            raise ValueError(f"max_merges {max_merges!r} out of range: need an int >= 0")
        path = Path(bpe_path)
        if not path.is_file():
            raise FileNotFoundError(
                f"CLIP BPE merges file {str(path)!r} not found; point bpe_path at a local copy of "
                "bpe_simple_vocab_16e6.txt.gz (see docs/how-to/clip-weights.md)"
            )
        raw = gzip.open(path).read() if path.name.endswith(".gz") else path.read_bytes()
        try:
            lines = raw.decode("utf-8").split("\n")
        except UnicodeDecodeError as e:
            raise ValueError(f"CLIP BPE merges file {str(path)!r} is not UTF-8 text: {e}") from e
        merges: list[tuple[str, str]] = []
        # Line 0 is the '#version' header; empty lines (the trailing newline) carry no merge.
        for lineno, line in enumerate(lines[1:], start=2):
            if len(merges) >= max_merges:
                break
            if not line.strip():
                continue
            parts = line.split()
            if len(parts) != 2:
                raise ValueError(
                    f"CLIP BPE merges file {str(path)!r} line {lineno}: expected two symbols separated "
                    f"by a space, got {line[:80]!r}"
                )
            merges.append((parts[0], parts[1]))

        self.bpe_path = path
        self.context_length = context_length
        self.byte_encoder = bytes_to_unicode()
        self.byte_decoder = {v: k for k, v in self.byte_encoder.items()}
        vocab = list(self.byte_encoder.values())
        vocab += [v + "</w>" for v in vocab]
        vocab += ["".join(m) for m in merges]
        vocab += [SOT_TEXT, EOT_TEXT]
        self.encoder: dict[str, int] = {}
        for i, sym in enumerate(vocab):
            self.encoder.setdefault(sym, i)  # a duplicated merge keeps its first id (as in CLIP)
        self.decoder: dict[int, str] = {i: sym for i, sym in enumerate(vocab)}
        self.bpe_ranks = {m: i for i, m in reversed(list(enumerate(merges)))}
        self._cache: dict[str, str] = {SOT_TEXT: SOT_TEXT, EOT_TEXT: EOT_TEXT}
        self.vocab_size = len(vocab)
        self.sot_token = self.encoder[SOT_TEXT]
        self.eot_token = self.encoder[EOT_TEXT]

    def bpe(self, token: str) -> str:
        """Merge the byte symbols of one pre-tokenised piece; returns its symbols joined by spaces."""
        cached = self._cache.get(token)
        if cached is not None:
            return cached
        word: tuple[str, ...] = tuple(token[:-1]) + (token[-1] + "</w>",)
        pairs = _pairs(word)
        if not pairs:
            return token + "</w>"
        while True:
            bigram = min(pairs, key=lambda p: self.bpe_ranks.get(p, float("inf")))
            if bigram not in self.bpe_ranks:
                break
            first, second = bigram
            merged: list[str] = []
            i = 0
            while i < len(word):
                try:
                    j = word.index(first, i)
                except ValueError:
                    merged.extend(word[i:])
                    break
                merged.extend(word[i:j])
                i = j
                if i < len(word) - 1 and word[i + 1] == second:
                    merged.append(first + second)
                    i += 2
                else:
                    merged.append(word[i])
                    i += 1
            word = tuple(merged)
            if len(word) == 1:
                break
            pairs = _pairs(word)
        out = " ".join(word)
        self._cache[token] = out
        return out

    def encode(self, text: str) -> list[int]:
        """Token ids of ``text`` (cleaned and lower-cased), without SOT/EOT."""
        if not isinstance(text, str):
            raise TypeError(f"text must be a str, got {type(text).__name__}")
        ids: list[int] = []
        for piece in _PATTERN.findall(clean_text(text)):
            sym = "".join(self.byte_encoder[b] for b in piece.encode("utf-8"))
            ids.extend(self.encoder[s] for s in self.bpe(sym).split(" "))
        return ids

    def decode(self, tokens: Sequence[int]) -> str:
        """Text of token ids; every end of word becomes one space (CLIP's decode).

        Raises:
            ValueError: an id is outside ``0..vocab_size-1``.
        """
        syms = []
        for t in tokens:
            t = int(t)
            if t not in self.decoder:
                raise ValueError(f"token id {t} out of range 0..{self.vocab_size - 1}")
            syms.append(self.decoder[t])
        # Every vocabulary symbol (including '</w>', SOT and EOT) is made of byte characters.
        raw = bytearray(self.byte_decoder[c] for c in "".join(syms))
        return raw.decode("utf-8", errors="replace").replace("</w>", " ")

    def tokenize(self, texts: Sequence[str], context_length: int | None = None) -> np.ndarray:
        """Texts -> (N, context_length) int64 rows ``[SOT] tokens [EOT] 0 ...``.

        A text longer than the context is truncated to ``context_length`` tokens whose last one is
        EOT (open_clip's behaviour), so the text tower always finds its EOT.
        """
        if isinstance(texts, str):
            raise TypeError("texts must be a sequence of strings, got a str; pass [text]")
        length = self.context_length if context_length is None else context_length
        if not isinstance(length, int) or length < 2:
            raise ValueError(f"context_length {length!r} out of range: need an int >= 2 (SOT + EOT)")
        out = np.zeros((len(texts), length), dtype=np.int64)  # (N, L)
        for row, text in enumerate(texts):
            ids = [self.sot_token, *self.encode(text), self.eot_token]
            if len(ids) > length:
                ids = ids[:length]
                ids[-1] = self.eot_token
            out[row, : len(ids)] = ids
        return out
