-- Error per axis and root-sum-square against the number of stars observed, over the successful
-- cases (the data behind the reference's Figures 9 and 10).
-- Full scan of star_cases.  `star report` reads star_summ_error_vs_observed.sql (the per-shard summaries, same numbers) when
-- every shard of the run has one, and this file for runs made before the summaries (jobs/reports/star.py).
SELECT
    n_observed                                                         AS stars_observed,
    count(*)                                                           AS cases,
    avg(abs(err_x_rad)) * arcsec_per_rad()                           AS mean_err_x_arcsec,
    avg(abs(err_y_rad)) * arcsec_per_rad()                           AS mean_err_y_arcsec,
    avg(abs(err_z_rad)) * arcsec_per_rad()                           AS mean_err_z_arcsec,
    avg(sqrt(err_x_rad ^ 2 + err_y_rad ^ 2 + err_z_rad ^ 2)) * arcsec_per_rad() AS mean_rss_arcsec
FROM star_cases
WHERE run = $run AND status = 'success'
GROUP BY n_observed
ORDER BY n_observed;
