-- Case counts per outcome, by the reference's method and with the final attitude check.
-- Full scan of star_cases.  `star report` reads star_summ_status.sql (the per-shard summaries, same numbers) when
-- every shard of the run has one, and this file for runs made before the summaries (jobs/reports/star.py).
SELECT status, status_robust, count(*) AS cases, avg(T) AS mean_T, avg(n_generated) AS mean_generated,
       avg(n_observed) AS mean_observed
FROM star_cases
WHERE run = $run
GROUP BY ALL
ORDER BY cases DESC, status, status_robust;
