"""Unicode NFC normalisation in the CLIP tokenizer: composed and decomposed text tokenise alike."""

from __future__ import annotations

import unicodedata
from pathlib import Path

import pytest

from mapper.ov.clip_tokenizer import ClipTokenizer, clean_text
from tests.mapper.ov.test_clip_backend import write_bpe

DECOMPOSED = "cafe\u0301"  # 'e' + COMBINING ACUTE ACCENT
COMPOSED = "caf\u00e9"  # 'é' as one code point


@pytest.fixture(scope="module")
def tokenizer(tmp_path_factory: pytest.TempPathFactory) -> ClipTokenizer:
    root: Path = tmp_path_factory.mktemp("nfc")
    # merges that build the composed word (é is the two UTF-8 bytes c3 a9, shown as 'Ã©')
    return ClipTokenizer(write_bpe(root / "bpe.txt.gz", ["c a", "ca f", "Ã ©</w>", "caf Ã©</w>"]))


def test_decomposed_and_composed_text_give_the_same_tokens(tokenizer: ClipTokenizer) -> None:
    assert DECOMPOSED != COMPOSED and unicodedata.normalize("NFC", DECOMPOSED) == COMPOSED
    assert clean_text(DECOMPOSED) == COMPOSED
    ids = tokenizer.encode(COMPOSED)
    assert ids == [tokenizer.encoder["cafÃ©</w>"]]  # one merged symbol
    assert tokenizer.encode(DECOMPOSED) == ids
    assert tokenizer.tokenize([DECOMPOSED]).tolist() == tokenizer.tokenize([COMPOSED]).tolist()
    assert tokenizer.decode(ids) == COMPOSED + " "
    # without NFC the combining accent's bytes (cc 81) would be symbols of their own
    assert len(tokenizer.encode("cafe")) == 2 and tokenizer.encode("cafe") != ids

