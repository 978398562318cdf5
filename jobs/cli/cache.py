"""``dualsight cache list`` and ``dualsight cache clear``: the cache folder of derived catalogs
(``$DUALSIGHT_CACHE``, else ``~/.cache/dualsight``), its entries, size and limit, and removing them.

What an entry is, its last use and the size limit (``$DUALSIGHT_CACHE_GB``) are
:mod:`dualsight.catalogs.cache_budget`'s; Taichi's kernel cache (the ``taichi/`` sub-folder) is shown apart and
removed only with ``clear --taichi``.  Entries in use (this process, or another one building them) and files that
are not dualsight's are never removed.  numpy-free: the command starts in a fraction of a second.
"""

from __future__ import annotations

import argparse
import json
import shutil
import sys
import time

from dualsight.catalogs.cache import cache_dir
from dualsight.catalogs.cache_budget import (CACHE_GB_ENV, TAICHI_FOLDER, cache_limit, folder_size, list_entries,
                                             remove_entry)
from dualsight.errors import InputError

__all__ = ["register", "cmd_cache_list", "cmd_cache_clear", "human_size"]


def _days(text: str) -> float:
    try:
        x = float(text)
    except ValueError:
        x = -1.0
    if not 0 <= x <= 1e5:
        raise argparse.ArgumentTypeError(f"{text!r} is not a number of days in [0, 100000]")
    return x


def register(sub) -> None:
    """Add the ``cache`` command group (``cache list``, ``cache clear``) to the top-level sub-parsers."""
    cache = sub.add_parser("cache", help="the cache of derived catalogs (pair and star catalogs): list, clear",
                           description="The cache folder of derived catalogs ($DUALSIGHT_CACHE, else "
                                       "~/.cache/dualsight): list its entries, clear them.  Its size is held under "
                                       f"${CACHE_GB_ENV} GiB (default 2), least recently used out first.")
    csub = cache.add_subparsers(dest="cache_action", metavar="ACTION")
    p = csub.add_parser("list", help="every entry: kind, what it holds, size, last used; the total and the limit")
    p.add_argument("--json", action="store_true", help="print one JSON object instead of the table")
    p.set_defaults(func=cmd_cache_list)
    p = csub.add_parser("clear", help="remove entries (--all, or --older-than DAYS), and Taichi's kernels "
                                      "(--taichi)",
                        description="Remove cache entries.  Entries in use (being built by another process) and "
                                    "files that are not dualsight's are kept.  Give --all or --older-than (and/or "
                                    "--taichi).")
    p.add_argument("--older-than", type=_days, default=None, metavar="DAYS",
                   help="remove the entries last used more than DAYS days ago (e.g. 30; 0.5 = 12 hours)")
    p.add_argument("--all", action="store_true", help="remove every entry (not Taichi's kernels: see --taichi)")
    p.add_argument("--taichi", action="store_true",
                   help="also remove Taichi's compiled-kernel cache (the taichi/ sub-folder; recompiled on the next "
                        "run, ~10-30 s)")
    p.set_defaults(func=cmd_cache_clear)
    cache.set_defaults(func=lambda a: (cache.print_help(), 0)[1])


def human_size(n: float) -> str:
    """Bytes in binary units: ``512 B``, ``1.5 KiB``, ``12.0 MiB``, ``2.00 GiB``."""
    for unit, scale in (("GiB", 2**30), ("MiB", 2**20), ("KiB", 2**10)):
        if n >= scale:
            return f"{n / scale:.2f} {unit}" if unit == "GiB" else f"{n / scale:.1f} {unit}"
    return f"{int(n)} B"


def _when(t: float, now: float) -> str:
    age = max(0.0, now - t)
    ago = (f"{age / 86400:.1f} d" if age >= 86400 else f"{age / 3600:.1f} h" if age >= 3600 else
           f"{age / 60:.0f} min")
    return f"{time.strftime('%Y-%m-%d %H:%M', time.localtime(t))} ({ago} ago)"


def cmd_cache_list(args) -> int:
    """``dualsight cache list``: the entries, least recently used first, then the total against the limit."""
    folder = cache_dir()
    limit = cache_limit()
    entries = list_entries(folder)
    total = sum(e.size for e in entries)
    taichi = folder / TAICHI_FOLDER
    t_size = folder_size(taichi)[0] if taichi.is_dir() else 0
    now = time.time()
    if args.json:
        print(json.dumps({"folder": str(folder), "limit_bytes": limit, "total_bytes": total,
                          "taichi_bytes": t_size,
                          "entries": [{"kind": e.kind, "name": e.name, "summary": e.summary, "bytes": e.size,
                                       "last_used_unix": e.last_used, "temporary_bytes": e.temporary,
                                       "files": [str(p) for p in e.files]} for e in entries]}, indent=1))
        return 0
    if not folder.is_dir():
        print(f"no cache folder at {folder} (nothing cached yet)")
        return 0
    rows = [(e.kind, e.name, e.summary + (f" [{human_size(e.temporary)} left by a build]" if e.temporary else ""),
             human_size(e.size), _when(e.last_used, now)) for e in entries]
    head = ("kind", "entry", "holds", "size", "last used")
    widths = [max(len(str(r[k])) for r in [head, *rows]) for k in range(len(head))]
    for r in [head, *rows]:
        print("  ".join(str(c).ljust(w) if k < 3 else str(c).rjust(w) if k == 3 else str(c)
                        for k, (c, w) in enumerate(zip(r, widths))).rstrip())
    lim = f"limit {human_size(limit)} (${CACHE_GB_ENV})" if limit is not None else f"no limit (${CACHE_GB_ENV}=0)"
    print(f"{len(entries)} entries, {human_size(total)} in {folder}; {lim}; Taichi's kernels "
          f"{human_size(t_size)} apart (not counted; dualsight cache clear --taichi)")
    return 0


def cmd_cache_clear(args) -> int:
    """``dualsight cache clear``: remove the chosen entries (and Taichi's kernels with ``--taichi``)."""
    if not (args.all or args.older_than is not None or args.taichi):
        raise InputError("give --all, --older-than DAYS or --taichi (see dualsight cache clear --help)",
                         source="cache clear")
    if args.all and args.older_than is not None:
        raise InputError("give --all or --older-than, not both", source="cache clear")
    folder = cache_dir()
    now = time.time()
    removed, kept, freed = 0, [], 0
    if args.all or args.older_than is not None:
        cut = now - (args.older_than or 0.0) * 86400 if args.older_than is not None else None
        for e in list_entries(folder):
            if cut is not None and e.last_used >= cut:
                continue
            if not e.removable:
                kept.append(f"{e.name} (not dualsight's)")
            elif remove_entry(folder, e, now=now):
                removed += 1
                freed += e.size
            else:
                kept.append(f"{e.name} (in use or being built)")
    taichi = folder / TAICHI_FOLDER
    t_freed = 0
    if args.taichi and taichi.is_dir() and not taichi.is_symlink():
        t_freed = folder_size(taichi)[0]
        shutil.rmtree(taichi, ignore_errors=True)
    print(f"removed {removed} entries ({human_size(freed)})" + (f" and Taichi's kernels ({human_size(t_freed)})"
                                                                if args.taichi else "") + f" from {folder}")
    if kept:
        print(f"kept {len(kept)}: " + ", ".join(kept[:5]) + (f" and {len(kept) - 5} more" if len(kept) > 5 else ""),
              file=sys.stderr)
    return 0
