-- Star hardware-in-the-loop run: the unknown objects of every image (detections no catalog star explains, at
-- least the run's unknown.mag_limit bright) and the --target's object, SI units, per image brightest first.
SELECT * EXCLUDE (run)
FROM hil_star_objects
WHERE run = $run
ORDER BY case_id, det_index;
