-- star_robust.sql from the per-shard partial aggregates (star_summaries; see star_summ_summary.sql).
SELECT method, success_rate, confident_wrong_rate, no_solution_rate, identification_rate,
       mean_err_x_arcsec, mean_err_y_arcsec, mean_err_z_arcsec FROM (
    SELECT 1 AS k, 'reference (paper)' AS method,
           coalesce(sum(cases) FILTER (WHERE status = 'success'), 0)::DOUBLE
               / nullif(sum(cases) FILTER (WHERE status IS NOT NULL), 0) AS success_rate,
           coalesce(sum(cases) FILTER (WHERE status = 'confident_wrong'), 0)::DOUBLE
               / nullif(sum(cases) FILTER (WHERE status IS NOT NULL), 0) AS confident_wrong_rate,
           coalesce(sum(cases) FILTER (WHERE status = 'no_solution'), 0)::DOUBLE
               / nullif(sum(cases) FILTER (WHERE status IS NOT NULL), 0) AS no_solution_rate,
           sum(sum_id_correct)::DOUBLE / nullif(sum(n_id_correct), 0) AS identification_rate,
           sum(sum_abs_err_x_rad) FILTER (WHERE status = 'success')
               / nullif(sum(n_abs_err_x_rad) FILTER (WHERE status = 'success'), 0) * arcsec_per_rad() AS mean_err_x_arcsec,
           sum(sum_abs_err_y_rad) FILTER (WHERE status = 'success')
               / nullif(sum(n_abs_err_y_rad) FILTER (WHERE status = 'success'), 0) * arcsec_per_rad() AS mean_err_y_arcsec,
           sum(sum_abs_err_z_rad) FILTER (WHERE status = 'success')
               / nullif(sum(n_abs_err_z_rad) FILTER (WHERE status = 'success'), 0) * arcsec_per_rad() AS mean_err_z_arcsec
    FROM star_summaries WHERE run = $run
    UNION ALL
    SELECT 2, 'robust (dualsight)',
           coalesce(sum(cases) FILTER (WHERE status_robust = 'success'), 0)::DOUBLE / nullif(sum(cases), 0),
           coalesce(sum(cases) FILTER (WHERE status_robust = 'confident_wrong'), 0)::DOUBLE / nullif(sum(cases), 0),
           coalesce(sum(cases) FILTER (WHERE status_robust = 'no_solution'), 0)::DOUBLE / nullif(sum(cases), 0),
           sum(sum_id_correct_robust)::DOUBLE / nullif(sum(n_id_correct_robust), 0),
           sum(sum_abs_err_x_robust_rad) FILTER (WHERE status_robust = 'success')
               / nullif(sum(n_abs_err_x_robust_rad) FILTER (WHERE status_robust = 'success'), 0) * arcsec_per_rad(),
           sum(sum_abs_err_y_robust_rad) FILTER (WHERE status_robust = 'success')
               / nullif(sum(n_abs_err_y_robust_rad) FILTER (WHERE status_robust = 'success'), 0) * arcsec_per_rad(),
           sum(sum_abs_err_z_robust_rad) FILTER (WHERE status_robust = 'success')
               / nullif(sum(n_abs_err_z_robust_rad) FILTER (WHERE status_robust = 'success'), 0) * arcsec_per_rad()
    FROM star_summaries WHERE run = $run AND status_robust IS NOT NULL
)
ORDER BY k;
