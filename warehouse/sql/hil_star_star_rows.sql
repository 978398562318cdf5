-- Star hardware-in-the-loop run: every column of every identified star (SI units), per image in the order
-- the detector found them (brightest first).
SELECT * EXCLUDE (run)
FROM hil_star_stars
WHERE run = $run
ORDER BY case_id, det_index;
