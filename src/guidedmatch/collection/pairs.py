"""Which image pairs of a collection to match: exhaustive, sequential (COLMAP's semantics), retrieval (the
collection's own visual words, :mod:`~guidedmatch.collection.retrieval`), a pairs file, or a union of these.

Every constructor returns a :class:`PairList`: the pairs to match, each unordered pair once, in a deterministic
order, plus a ``report`` of the normalizations applied to the input (self-pairs, duplicates and the second order
of a pair given both ways are dropped and counted with a few examples). Names a caller passes that the feature
source does not know are an :class:`~guidedmatch.errors.InputError` naming them, raised before any work.

The order of a pair is kept as first given (``(a, b)`` matches image ``a`` against image ``b``); sinks store it in
their own convention (COLMAP: smaller image id first; hloc: both orders are looked up).
"""
from __future__ import annotations

import os
from collections.abc import Iterable, Sequence
from dataclasses import dataclass, field
from pathlib import Path

from ..errors import ConfigError, InputError

__all__ = ["Pair", "PairList", "exhaustive_pairs", "sequential_pairs", "read_pairs_file", "pairs_from_spec",
           "normalize_pairs"]

Pair = tuple[str, str]

_EXAMPLES = 5  # examples kept per normalization kind in the report


@dataclass(frozen=True)
class PairList:
    """Pairs to match and what was normalized to get them.

    Attributes:
        pairs: ``((name1, name2), ...)``, each unordered pair once, no self-pairs.
        report: ``{"input": n_given, "pairs": n_kept, "self_pairs": {"count", "examples"},
            "duplicates": {...}, "reversed_duplicates": {...}}`` (``examples`` are up to 5 offending pairs,
            with ``line`` numbers for a pairs file) plus ``"source"`` (how the list was made).
    """

    pairs: tuple[Pair, ...]
    report: dict = field(default_factory=dict)

    def __len__(self) -> int:
        return len(self.pairs)

    def __iter__(self):
        return iter(self.pairs)

    def names(self) -> list[str]:
        """Image names used by at least one pair, in first-use order."""
        return list(dict.fromkeys(n for p in self.pairs for n in p))

    def summary(self) -> str:
        """One line: pairs kept and each normalization with its count (``""`` parts omitted)."""
        r = self.report
        parts = [f"{len(self.pairs)} pairs ({r.get('source', 'given')})"]
        for key, label in (("self_pairs", "self-pairs"), ("duplicates", "duplicates"),
                           ("reversed_duplicates", "reversed duplicates")):
            n = r.get(key, {}).get("count", 0)
            if n:
                parts.append(f"{n} {label} dropped")
        return ", ".join(parts)


def _check_names(names: Sequence[str]) -> list[str]:
    names = [str(n) for n in names]
    seen: set[str] = set()
    dup = [n for n in names if n in seen or seen.add(n)]
    if dup:
        raise InputError(f"image names must be unique; repeated: {', '.join(sorted(set(dup))[:_EXAMPLES])}")
    return names


def normalize_pairs(pairs: Iterable[Pair], names: Sequence[str] | None = None, *, source: str = "given",
                    lines: Sequence[int] | None = None) -> PairList:
    """Drop self-pairs, duplicates and reversed duplicates (first occurrence kept), check names.

    Args:
        pairs: ``(name1, name2)`` tuples.
        names: the images the source has; a pair naming another image raises :class:`InputError` listing the
            unknown names (None = no check).
        source: how the pairs were made, stored in the report.
        lines: optional line number of each pair (pairs files), used in error messages and report examples.

    >>> pl = normalize_pairs([("a", "b"), ("b", "a"), ("a", "a"), ("a", "b"), ("b", "c")], ["a", "b", "c"])
    >>> pl.pairs
    (('a', 'b'), ('b', 'c'))
    >>> pl.report["reversed_duplicates"]["count"], pl.report["duplicates"]["count"], pl.report["self_pairs"]["count"]
    (1, 1, 1)
    """
    pairs = [(str(a), str(b)) for a, b in pairs]
    where = (lambda k: f"line {lines[k]}") if lines is not None else (lambda k: f"pair {k + 1}")
    if names is not None:
        known = set(_check_names(names))
        unknown: dict[str, str] = {}
        for k, (a, b) in enumerate(pairs):
            for n in (a, b):
                if n not in known and n not in unknown:
                    unknown[n] = where(k)
        if unknown:
            shown = ", ".join(f"{n!r} ({w})" for n, w in list(unknown.items())[:10])
            more = f" and {len(unknown) - 10} more" if len(unknown) > 10 else ""
            raise InputError(f"{len(unknown)} image name(s) in the pairs ({source}) are not in the feature source: "
                             f"{shown}{more}")
    kept: list[Pair] = []
    seen: set[Pair] = set()
    report = {"source": source, "input": len(pairs)}
    counts = {"self_pairs": [], "duplicates": [], "reversed_duplicates": []}
    for k, (a, b) in enumerate(pairs):
        if a == b:
            counts["self_pairs"].append((k, (a, b)))
        elif (a, b) in seen:
            counts["duplicates"].append((k, (a, b)))
        elif (b, a) in seen:
            counts["reversed_duplicates"].append((k, (a, b)))
        else:
            seen.add((a, b))
            kept.append((a, b))
    for key, items in counts.items():
        ex = [{"pair": list(p), "at": where(k)} for k, p in items[:_EXAMPLES]]
        report[key] = {"count": len(items), "examples": ex}
    report["pairs"] = len(kept)
    return PairList(tuple(kept), report)


def exhaustive_pairs(names: Sequence[str]) -> PairList:
    """Every unordered pair ``(names[i], names[j])``, ``i < j`` (``N (N - 1) / 2`` pairs, held in memory).

    >>> exhaustive_pairs(["a", "b", "c"]).pairs
    (('a', 'b'), ('a', 'c'), ('b', 'c'))
    """
    names = _check_names(names)
    pairs = tuple((names[i], names[j]) for i in range(len(names)) for j in range(i + 1, len(names)))
    report = {"source": "exhaustive", "input": len(pairs), "pairs": len(pairs)}
    report.update({k: {"count": 0, "examples": []} for k in ("self_pairs", "duplicates", "reversed_duplicates")})
    return PairList(pairs, report)


def sequential_pairs(names: Sequence[str], overlap: int = 10, quadratic: bool = False, *,
                     order: str = "name") -> PairList:
    """Each image with its ``overlap`` successors, as COLMAP's sequential matcher pairs them.

    COLMAP (``SequentialPairGenerator``, colmap/controllers/pairing.cc) orders the images by name and pairs image
    ``i`` with ``i + 1, ..., i + overlap`` -- or, with ``quadratic_overlap``, with ``i + 2^0, i + 2^1, ...,
    i + 2^(overlap - 1)`` (only the powers of two, COLMAP 3.11 to 4.x) -- stopping at the end of the sequence.

    Args:
        names: image names.
        overlap: ``K >= 1`` successors (or powers of two) per image (COLMAP default 10).
        quadratic: COLMAP's ``quadratic_overlap`` (COLMAP's default is True; ours is False, the plain K-window).
        order: ``"name"`` sorts by name like COLMAP; ``"given"`` keeps the order of ``names`` (e.g. video frames
            whose names do not sort in time).

    >>> sequential_pairs(["c", "a", "b", "d"], overlap=2).pairs
    (('a', 'b'), ('a', 'c'), ('b', 'c'), ('b', 'd'), ('c', 'd'))
    >>> [p for p in sequential_pairs([f"{i:02d}" for i in range(9)], 3, quadratic=True).pairs if p[0] == "00"]
    [('00', '01'), ('00', '02'), ('00', '04')]
    """
    from ..validation import check_bool, check_choice, check_number

    check_number("sequential_pairs", "overlap", overlap, lo=1, integer=True)
    check_bool("sequential_pairs", "quadratic", quadratic)
    check_choice("sequential_pairs", "order", order, ("name", "given"))
    names = _check_names(names)
    seq = sorted(names) if order == "name" else names
    n = len(seq)
    pairs = []
    for i in range(n):
        for k in range(int(overlap)):
            j = i + (1 << k) if quadratic else i + k + 1
            if j >= n:
                break
            pairs.append((seq[i], seq[j]))
    src = f"sequential:{overlap}" + (":quadratic" if quadratic else "")
    return normalize_pairs(pairs, None, source=src)


def read_pairs_file(path: str | os.PathLike, names: Sequence[str] | None) -> PairList:
    """Read a COLMAP / hloc pairs file: ``name1 name2`` per line (whitespace separated).

    Blank lines and lines starting with ``#`` are skipped; a line with another number of fields, a missing file,
    a file without any pair, or names the source does not have (``names``) raise :class:`InputError` with line
    numbers. Duplicates,
    reversed duplicates and self-pairs are dropped and reported (see :func:`normalize_pairs`). Image names
    cannot contain whitespace (neither COLMAP's nor hloc's reader allows it).
    """
    path = Path(path)
    if not path.exists():
        raise InputError(f"pairs file not found: {path}")
    if path.is_dir():
        raise InputError(f"pairs file is a directory: {path}")
    try:
        text = path.read_text(encoding="utf-8")
    except UnicodeDecodeError as exc:
        raise InputError(f"pairs file {path} is not UTF-8 text ({exc.reason} at byte {exc.start})") from None
    pairs, lines = [], []
    for lineno, line in enumerate(text.splitlines(), 1):
        s = line.strip()
        if not s or s.startswith("#"):
            continue
        fields = s.split()
        if len(fields) != 2:
            raise InputError(f"{path}:{lineno}: expected 'name1 name2', got {len(fields)} field(s): {s[:120]!r}")
        pairs.append((fields[0], fields[1]))
        lines.append(lineno)
    if not pairs:  # most likely the wrong file, or one cut off by a failed write: say so rather than match nothing
        raise InputError(f"pairs file {path} has no 'name1 name2' line")
    return normalize_pairs(pairs, names, source=f"file {path.name}", lines=lines)


def write_pairs_file(path: str | os.PathLike, pairs: Iterable[Pair]) -> None:
    """Write ``name1 name2`` lines (atomically: temp file + rename)."""
    from ..features import atomic_write_text

    atomic_write_text(path, "".join(f"{a} {b}\n" for a, b in pairs))


def has_retrieval(spec: str) -> bool:
    """Whether a pair spec has a ``retrieval`` part (a pairs file never has).

    >>> has_retrieval("sequential:5+retrieval:20"), has_retrieval("exhaustive")
    (True, False)
    """
    spec = str(spec)
    return not Path(spec).exists() and any(p.strip().split(":")[0] == "retrieval" for p in spec.split("+"))


def check_pairs_spec(spec: str, names: Sequence[str]) -> None:
    """Fail now (ConfigError / InputError) on a spec :func:`pairs_from_spec` would refuse, without computing
    anything expensive: retrieval parts are only parsed (their pairs need the features).

    >>> check_pairs_spec("sequential:2+retrieval:5", ["a", "b", "c"])
    >>> check_pairs_spec("retrieval:0", ["a", "b"])
    Traceback (most recent call last):
    ...
    guidedmatch.errors.ConfigError: pairs spec 'retrieval:0': expected retrieval[:K] with an integer K >= 1 (images kept per image), got '0'
    """
    spec = str(spec).strip()
    parts = [p.strip() for p in spec.split("+")] if "+" in spec and not Path(spec).exists() else [spec]
    if any(not p for p in parts):
        raise ConfigError(f"pairs spec {spec!r}: an empty part between '+' signs")
    for part in parts:
        if part == "retrieval" or part.startswith("retrieval:"):
            from .retrieval import parse_retrieval_spec

            parse_retrieval_spec(part)
        else:
            pairs_from_spec(part, names)


def pairs_from_spec(spec: str, names: Sequence[str], source=None, *, retrieval=None,
                    retrieval_cache=True) -> PairList:
    """Pairs from a CLI spec: ``"exhaustive"``, ``"sequential"`` (K = 10), ``"sequential:K"``,
    ``"sequential:K:quadratic"``, ``"retrieval"`` / ``"retrieval:K"`` (the K most similar images of every image by
    the collection's own visual words, :mod:`guidedmatch.collection.retrieval`; needs ``source``), the path of a
    pairs file, or several of these joined by ``+`` (their union, e.g. ``"sequential:5+retrieval:20"``).

    Args:
        spec: the spec.
        names: the images (of ``source``).
        source: the feature source; required by ``retrieval`` specs (its descriptors give the similarities).
        retrieval: :class:`~guidedmatch.collection.retrieval.RetrievalConfig` fields (dict) for ``retrieval`` specs
            (``k`` comes from the spec).
        retrieval_cache: where the retrieval stage saves its vocabulary and shortlist (True: next to the source's
            file; a path; None: nowhere).

    The report of a list with a retrieval part has ``"retrieval"``: the stage's facts (time, words, reused ...).

    >>> len(pairs_from_spec("sequential:2", ["a", "b", "c", "d"]))
    5
    >>> pairs_from_spec("sequential:1+exhaustive", ["a", "b", "c"]).report["source"]
    'sequential:1+exhaustive'
    """
    spec = str(spec).strip()
    if "+" in spec and not Path(spec).exists():
        parts = [p.strip() for p in spec.split("+")]
        if any(not p for p in parts):
            raise ConfigError(f"pairs spec {spec!r}: an empty part between '+' signs")
        lists = [pairs_from_spec(p, names, source, retrieval=retrieval, retrieval_cache=retrieval_cache)
                 for p in parts]
        merged = normalize_pairs([pr for pl in lists for pr in pl.pairs], None, source=spec)
        report = dict(merged.report)
        report["duplicates"] = {"count": 0, "examples": []}  # overlap between the parts is expected, not an error
        report["reversed_duplicates"] = {"count": 0, "examples": []}
        report["parts"] = {pl.report.get("source", p): len(pl) for p, pl in zip(parts, lists)}
        for pl in lists:
            if "retrieval" in pl.report:
                report["retrieval"] = pl.report["retrieval"]
        return PairList(merged.pairs, report)
    if spec == "exhaustive":
        return exhaustive_pairs(names)
    if spec == "retrieval" or spec.startswith("retrieval:"):
        from .retrieval import parse_retrieval_spec, retrieval_pairs

        k = parse_retrieval_spec(spec)
        if source is None:
            raise ConfigError(f"pairs spec {spec!r} needs the feature source (its descriptors): "
                              "pairs_from_spec(spec, names, source)")
        res = retrieval_pairs(source, names, {**(retrieval or {}), "k": k}, cache=retrieval_cache)
        pl = normalize_pairs(res.pairs, None, source=f"retrieval:{k}")
        return PairList(pl.pairs, {**pl.report, "retrieval": res.info})
    if spec == "sequential" or spec.startswith("sequential:"):
        parts = spec.split(":")
        k = 10
        quadratic = False
        try:
            if len(parts) >= 2 and parts[1]:
                k = int(parts[1])
            if len(parts) == 3 and parts[2] == "quadratic":
                quadratic = True
            elif len(parts) > 2:
                raise ValueError(parts[2:])
        except ValueError:
            raise ConfigError(f"pairs spec {spec!r}: expected sequential[:K[:quadratic]] with an integer K") from None
        return sequential_pairs(names, k, quadratic)
    if not Path(spec).exists():
        raise InputError(f"pairs {spec!r}: not 'exhaustive', 'sequential[:K[:quadratic]]', 'retrieval[:K]', "
                         "several of these joined by '+', or an existing pairs file")
    return read_pairs_file(spec, names)
