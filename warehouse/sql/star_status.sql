-- Case counts per outcome, by the reference's method and with the final attitude check.
SELECT status, status_robust, count(*) AS cases, avg(T) AS mean_T, avg(n_generated) AS mean_generated,
       avg(n_observed) AS mean_observed
FROM star_cases
WHERE run = $run
GROUP BY ALL
ORDER BY cases DESC;
