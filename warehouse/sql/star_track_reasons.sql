-- Star tracking: why tracking did not hold, by frame event (lock_reason: locked, no_prior, too_few_matches,
-- degenerate, residual, p_chance, no_image) and what the frame's mode became.  One run ($run).
SELECT event, lock_reason, mode, count(*) AS frames
FROM star_frames
WHERE run = $run
GROUP BY ALL
ORDER BY event, lock_reason, mode;
