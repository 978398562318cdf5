-- star_error_vs_observed.sql from the per-shard partial aggregates (star_summaries; see star_summ_summary.sql):
-- the summaries are grouped by the exact number of stars observed, so each row here sums that group over shards.
SELECT
    n_observed                                                                        AS stars_observed,
    sum(cases)::BIGINT                                                                AS cases,
    sum(sum_abs_err_x_rad) / nullif(sum(n_abs_err_x_rad), 0) * arcsec_per_rad()     AS mean_err_x_arcsec,
    sum(sum_abs_err_y_rad) / nullif(sum(n_abs_err_y_rad), 0) * arcsec_per_rad()     AS mean_err_y_arcsec,
    sum(sum_abs_err_z_rad) / nullif(sum(n_abs_err_z_rad), 0) * arcsec_per_rad()     AS mean_err_z_arcsec,
    sum(sum_rss_err_rad) / nullif(sum(n_rss_err_rad), 0) * arcsec_per_rad()         AS mean_rss_arcsec
FROM star_summaries
WHERE run = $run AND status = 'success'
GROUP BY n_observed
ORDER BY n_observed;
