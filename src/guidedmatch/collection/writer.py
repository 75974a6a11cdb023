"""The one writer of a collection run: every pair's result goes through :class:`_Writer` in this process -- the sink
write (one transaction per pair), the retries and the failed list, the per-pair log line and report record, the
progress bar and the totals. :class:`_NoBar` stands in for the progress bar when there is none.
"""
from __future__ import annotations

import collections
import json

from .config import CollectionConfig
from .planning import _Queue
from .report import PairOutcome, _json_default


class _Writer:
    """The one writer: sink writes, retries, the failed list, per-pair log lines, progress and totals."""

    def __init__(self, sink, cfg: CollectionConfig, queue: _Queue, bar, log, memos=None):
        self.sink, self.cfg, self.queue, self.bar, self.log = sink, cfg, queue, bar, log
        self.memos = memos  # the run's StartMemos (memos.py): returned memos kept, memo hits counted
        self.attempts: collections.Counter = collections.Counter()
        self.errors: dict[frozenset, list] = {}
        self.done = 0
        self.failed: list = []
        self.per_pair: list = []
        self.sums = collections.Counter()
        self.verdicts = collections.Counter()
        self.quarantined: set = set()

    def handle(self, out: PairOutcome, *, task_failed: bool = False, alone: bool = True) -> None:
        """Write a done pair; requeue or report a failed one.

        ``task_failed``: the whole task failed (its worker died, ...), not the pair's own code. When that task ran
        next to others (``alone=False``) the pair may be a bystander of another pair that killed the worker: it is
        put in quarantine (run later alone, one task on the whole cluster) without counting an attempt.
        """
        key = frozenset((out.name1, out.name2))
        if not out.ok:
            self.errors.setdefault(key, []).append(out.reason)
            if task_failed and not alone and key not in self.quarantined:
                self.quarantined.add(key)
                self.queue.suspects.append([(out.name1, out.name2)])
                return
            self.attempts[key] += 1
            if self.attempts[key] <= self.cfg.retries:
                (self.queue.suspects if task_failed else self.queue.retry).append([(out.name1, out.name2)])
                return
            self.failed.append(((out.name1, out.name2), out.reason))
            self._record(out, dict(status="failed", reason=out.reason))
            return
        self.attempts[key] += 1
        self.sink.write(out.name1, out.name2, out.pairs, out.scores, out.geometry)
        self.done += 1
        st = out.stats
        self.sums.update(matches=st["matches"], inliers=st["inliers"] if out.geometry else 0,
                         verified_pairs=int(bool(out.geometry)))
        for k in ("load_s", "match_s"):
            self.sums[k] += st[k]
        self.verdicts[st["verdict"]] += 1
        if self.memos is not None:
            self.memos.hits += st.get("start_memo_hits", 0)
            if out.memo is not None:
                self.memos.add((out.name1, out.name2), out.memo)
        self._record(out, dict(status="done"))

    def _record(self, out: PairOutcome, extra: dict) -> None:
        key = frozenset((out.name1, out.name2))
        rec = dict(pair=[out.name1, out.name2], **extra, attempts=self.attempts[key], **out.stats)
        if self.errors.get(key):
            rec["errors"] = self.errors[key]
        if len(self.per_pair) < self.cfg.report_max_pairs:
            self.per_pair.append(rec)
        if self.log is not None:
            self.log.write(json.dumps(dict(event="pair", **rec), default=_json_default) + "\n")
            self.log.flush()
        self.bar.update(1)
        if self.failed:
            self.bar.set_postfix(failed=len(self.failed), refresh=False)


class _NoBar:
    """The progress bar's interface, doing nothing (``progress=False``)."""

    def update(self, n: int = 1) -> None:
        pass

    def set_postfix(self, *args, **kwargs) -> None:
        pass

    def set_postfix_str(self, *args, **kwargs) -> None:
        pass

    def close(self) -> None:
        pass
