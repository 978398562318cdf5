-- Mean time per case of each pipeline stage and its share of the total.
-- Full scan of star_cases.  `star report` reads star_summ_stage_times.sql (the per-shard summaries, same numbers) when
-- every shard of the run has one, and this file for runs made before the summaries (jobs/reports/star.py).
WITH t AS (
    SELECT avg(t_sample_ns) AS sample, avg(t_render_ns) AS render, avg(t_detect_ns) AS detect,
           avg(t_identify_ns) AS identify, avg(t_attitude_ns) AS attitude, avg(t_robust_ns) AS robust, avg(t_total_ns) AS total
    FROM star_cases WHERE run = $run
)
SELECT stage, ms_per_case, ms_per_case / (total / 1e6) AS share FROM (
    SELECT 'sample' AS stage, sample / 1e6 AS ms_per_case, total FROM t
    UNION ALL SELECT 'render', render / 1e6, total FROM t
    UNION ALL SELECT 'detect', detect / 1e6, total FROM t
    UNION ALL SELECT 'identify', identify / 1e6, total FROM t
    UNION ALL SELECT 'attitude', attitude / 1e6, total FROM t
    UNION ALL SELECT 'robust method', robust / 1e6, total FROM t
)
ORDER BY ms_per_case DESC, stage;
