-- star_status.sql from the per-shard partial aggregates (star_summaries; see star_summ_summary.sql).
SELECT status, status_robust, sum(cases)::BIGINT AS cases,
       sum(sum_T)::DOUBLE / nullif(sum(n_T), 0)                           AS mean_T,
       sum(sum_stars_generated)::DOUBLE / nullif(sum(n_stars_generated), 0) AS mean_generated,
       sum(sum_stars_observed)::DOUBLE / nullif(sum(n_stars_observed), 0)   AS mean_observed
FROM star_summaries
WHERE run = $run
GROUP BY ALL
ORDER BY cases DESC, status, status_robust;
