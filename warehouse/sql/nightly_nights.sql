-- One row per night of the nightly_verdicts dataset: how many verdicts of each kind.
SELECT night,
       count(*)                                                          AS verdicts,
       count(*) FILTER (WHERE verdict = 'REGRESSION')                    AS regressions,
       count(*) FILTER (WHERE verdict IN ('not comparable', 'no baseline', 'failed')) AS not_comparable,
       count(*) FILTER (WHERE verdict = 'identical')                     AS identical,
       count(*) FILTER (WHERE verdict = 'ok')                            AS ok,
       count(*) FILTER (WHERE verdict = 'improved')                      AS improved
FROM nightly_verdicts
GROUP BY night
ORDER BY night;
