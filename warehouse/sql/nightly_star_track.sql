-- Nightly metrics of one star-tracking run ($run), one row per sequence (jobs/nightly/compare.py:
-- METRICS["star_track"]); a sequence, not a frame, is the unit of the tests: its frames are not independent (a
-- blinded frame and its re-acquisition come together).  NULL = not applicable to this sequence.
--   availability        share of the sequence's frames with a valid attitude within the error limit
--   false_lock          the sequence had at least one valid attitude beyond the limit
--   rate_err_deg_s      RMS over the sequence's frames of |rate from two fixes - true mean rate| (deg/s)
--   err_total_arcsec    RMS over the sequence's frames with an attitude of the total attitude error (arcsec)
WITH f AS (
    SELECT case_id, sqrt(avg(err_total_arcsec * err_total_arcsec)) AS err_total_arcsec
    FROM star_frames
    WHERE run = $run AND err_total_arcsec IS NOT NULL
    GROUP BY case_id
)
SELECT s.case_id,
       s.availability,
       s.false_locks > 0                  AS false_lock,
       s.rate_att_err_rms_deg_s           AS rate_err_deg_s,
       f.err_total_arcsec
FROM star_sequences s LEFT JOIN f USING (case_id)
WHERE s.run = $run
ORDER BY s.case_id;
