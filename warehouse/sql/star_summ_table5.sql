-- star_table5.sql from the per-shard partial aggregates (star_summaries; see star_summ_summary.sql): the
-- reference's Table 5, averages over the successful cases = sum of partial sums / sum of partial counts.
WITH s AS (
    SELECT sum(sum_stars_generated)::DOUBLE / nullif(sum(n_stars_generated), 0)      AS generated,
           sum(sum_stars_observed)::DOUBLE / nullif(sum(n_stars_observed), 0)        AS observed,
           sum(sum_T)::DOUBLE / nullif(sum(n_T), 0)                                  AS T,
           sum(sum_abs_err_x_rad) / nullif(sum(n_abs_err_x_rad), 0) * arcsec_per_rad() AS eps_x,
           sum(sum_abs_err_y_rad) / nullif(sum(n_abs_err_y_rad), 0) * arcsec_per_rad() AS eps_y,
           sum(sum_abs_err_z_rad) / nullif(sum(n_abs_err_z_rad), 0) * arcsec_per_rad() AS eps_z
    FROM star_summaries WHERE run = $run AND status = 'success'
)
SELECT metric, dualsight, reference FROM (
    SELECT 1 AS k, 'Stars generated' AS metric, generated AS dualsight, 11.4607 AS reference FROM s
    UNION ALL SELECT 2, 'Stars observed', observed, 10.1152 FROM s
    UNION ALL SELECT 3, 'T', T, 8.6230 FROM s
    UNION ALL SELECT 4, 'eps_x (arcsec)', eps_x, 10.6237 FROM s
    UNION ALL SELECT 5, 'eps_y (arcsec)', eps_y, 7.7998 FROM s
    UNION ALL SELECT 6, 'eps_z (arcsec)', eps_z, 6.4789 FROM s
)
ORDER BY k;
