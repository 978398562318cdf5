-- The reference's Table 5: average performance over the successful cases, beside the reference's values.
-- Full scan of star_cases.  `star report` reads star_summ_table5.sql (the per-shard summaries, same numbers) when
-- every shard of the run has one, and this file for runs made before the summaries (jobs/reports/star.py).
WITH s AS (
    SELECT * FROM star_cases WHERE run = $run AND status = 'success'
)
SELECT metric, dualsight, reference FROM (
    SELECT 1 AS k, 'Stars generated' AS metric, avg(n_generated) AS dualsight, 11.4607 AS reference FROM s
    UNION ALL SELECT 2, 'Stars observed', avg(n_observed), 10.1152 FROM s
    UNION ALL SELECT 3, 'T', avg(T), 8.6230 FROM s
    UNION ALL SELECT 4, 'eps_x (arcsec)', avg(abs(err_x_rad)) * arcsec_per_rad(), 10.6237 FROM s
    UNION ALL SELECT 5, 'eps_y (arcsec)', avg(abs(err_y_rad)) * arcsec_per_rad(), 7.7998 FROM s
    UNION ALL SELECT 6, 'eps_z (arcsec)', avg(abs(err_z_rad)) * arcsec_per_rad(), 6.4789 FROM s
)
ORDER BY k;
