-- Nightly "identical" check: do two runs ($a, $b) of one job kind have the same rows in dataset {dataset}?
-- Every column is compared except the run partition and the timing columns (t_*_ns), with EXCEPT ALL in
-- both directions (set semantics treat NULL = NULL and NaN = NaN; ALL also catches duplicated rows).
-- {dataset} is filled in by jobs/nightly/compare.py from the job module's own dataset names (never user text).
WITH a AS (SELECT COLUMNS(lambda c: NOT regexp_matches(c, '^(t_.*_ns|run)$')) FROM "{dataset}" WHERE run = $a),
     b AS (SELECT COLUMNS(lambda c: NOT regexp_matches(c, '^(t_.*_ns|run)$')) FROM "{dataset}" WHERE run = $b)
SELECT (SELECT count(*) FROM a)                                   AS rows_a,
       (SELECT count(*) FROM b)                                   AS rows_b,
       (SELECT count(*) FROM (SELECT * FROM a EXCEPT ALL SELECT * FROM b))  AS only_a,
       (SELECT count(*) FROM (SELECT * FROM b EXCEPT ALL SELECT * FROM a))  AS only_b;
