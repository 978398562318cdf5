-- star_stage_times.sql from the per-shard partial aggregates (star_summaries; see star_summ_summary.sql):
-- mean time per case of each stage = sum of the shards' time sums / number of cases that timed the stage.
WITH t AS (
    SELECT sum(t_sample_sum_ns)::DOUBLE / nullif(sum(n_t_sample_ns), 0)     AS sample,
           sum(t_render_sum_ns)::DOUBLE / nullif(sum(n_t_render_ns), 0)     AS render,
           sum(t_detect_sum_ns)::DOUBLE / nullif(sum(n_t_detect_ns), 0)     AS detect,
           sum(t_identify_sum_ns)::DOUBLE / nullif(sum(n_t_identify_ns), 0) AS identify,
           sum(t_attitude_sum_ns)::DOUBLE / nullif(sum(n_t_attitude_ns), 0) AS attitude,
           sum(t_robust_sum_ns)::DOUBLE / nullif(sum(n_t_robust_ns), 0)     AS robust,
           sum(t_total_sum_ns)::DOUBLE / nullif(sum(n_t_total_ns), 0)       AS total
    FROM star_summaries WHERE run = $run
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
