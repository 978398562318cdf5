-- star_summary.sql computed from the per-shard partial aggregates (dataset star_summaries: one row per shard and
-- (status, status_robust, n_observed); jobs/kinds/star_summaries.py) instead of scanning every case: each avg(x) of the
-- full scan is sum(sum_x) / sum(n_x) over the groups it covers, each rate a count of cases over a count of cases.
-- Same columns and numbers as star_summary.sql (counts and rates exactly; means to ~1e-16 relative).
-- The star_summ_*.sql files read the table star_summaries that jobs/star_report.open_summaries loads: the run's
-- summary files read once and summed per key, one column per sum (sum_<m>, t_<stage>_sum_ns) and per non-null count
-- (n_<m>) (not the lake's view of the same name, whose sums are packed in lists: jobs/star_summaries.unpack_sql).
SELECT
    coalesce(sum(cases), 0)::BIGINT                                                      AS cases,
    coalesce(sum(cases) FILTER (WHERE status = 'success'), 0)::DOUBLE
        / nullif(sum(cases) FILTER (WHERE status IS NOT NULL), 0)                        AS success_rate,
    coalesce(sum(cases) FILTER (WHERE status = 'confident_wrong'), 0)::DOUBLE
        / nullif(sum(cases) FILTER (WHERE status IS NOT NULL), 0)                        AS confident_wrong_rate,
    coalesce(sum(cases) FILTER (WHERE status = 'no_solution'), 0)::DOUBLE
        / nullif(sum(cases) FILTER (WHERE status IS NOT NULL), 0)                        AS no_solution_rate,
    sum(sum_id_correct)::DOUBLE / nullif(sum(n_id_correct), 0)                           AS identification_rate,
    coalesce(sum(cases) FILTER (WHERE status_robust = 'success'), 0)::DOUBLE
        / nullif(sum(cases) FILTER (WHERE status_robust IS NOT NULL), 0)                 AS robust_success_rate,
    coalesce(sum(cases) FILTER (WHERE status_robust = 'confident_wrong'), 0)::DOUBLE
        / nullif(sum(cases) FILTER (WHERE status_robust IS NOT NULL), 0)                 AS robust_confident_wrong_rate,
    coalesce(sum(cases) FILTER (WHERE status_robust = 'no_solution'), 0)::DOUBLE
        / nullif(sum(cases) FILTER (WHERE status_robust IS NOT NULL), 0)                 AS robust_no_solution_rate,
    sum(sum_id_correct_robust)::DOUBLE / nullif(sum(n_id_correct_robust), 0)             AS robust_identification_rate,
    sum(sum_stars_generated) FILTER (WHERE status = 'success')::DOUBLE
        / nullif(sum(n_stars_generated) FILTER (WHERE status = 'success'), 0)            AS mean_stars_generated,
    sum(sum_stars_observed) FILTER (WHERE status = 'success')::DOUBLE
        / nullif(sum(n_stars_observed) FILTER (WHERE status = 'success'), 0)             AS mean_stars_observed,
    sum(sum_T) FILTER (WHERE status = 'success')::DOUBLE
        / nullif(sum(n_T) FILTER (WHERE status = 'success'), 0)                          AS mean_T,
    sum(sum_abs_err_x_rad) FILTER (WHERE status = 'success')
        / nullif(sum(n_abs_err_x_rad) FILTER (WHERE status = 'success'), 0) * arcsec_per_rad() AS mean_err_x_arcsec,
    sum(sum_abs_err_y_rad) FILTER (WHERE status = 'success')
        / nullif(sum(n_abs_err_y_rad) FILTER (WHERE status = 'success'), 0) * arcsec_per_rad() AS mean_err_y_arcsec,
    sum(sum_abs_err_z_rad) FILTER (WHERE status = 'success')
        / nullif(sum(n_abs_err_z_rad) FILTER (WHERE status = 'success'), 0) * arcsec_per_rad() AS mean_err_z_arcsec,
    sum(sum_stars_generated)::DOUBLE / nullif(sum(n_stars_generated), 0)                 AS mean_stars_generated_all,
    sum(sum_ge3_stars)::DOUBLE / nullif(sum(n_ge3_stars), 0)                             AS sky_share_ge3_stars,
    sum(sum_ge4_stars)::DOUBLE / nullif(sum(n_ge4_stars), 0)                             AS sky_share_ge4_stars,
    sum(t_total_sum_ns)::DOUBLE / nullif(sum(n_t_total_ns), 0) / 1e6                     AS mean_ms_per_case
FROM star_summaries
WHERE run = $run;
