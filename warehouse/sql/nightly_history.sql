-- Every verdict of every night (dataset nightly_verdicts, one run per night), oldest night first:
-- the trend of each (job, comparison, metric).
SELECT night, job, comparison, metric, baseline, now, test, threshold_or_p, alpha, verdict, now_run, note
FROM nightly_verdicts
ORDER BY night, job, comparison, metric;
