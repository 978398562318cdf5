-- Trajectory run, frame by frame: true and estimated positions (the data behind the reference's Fig. 6).
SELECT frame, true_x_m, true_y_m, true_z_m, found, n_pixels, axis_ratio,
       paper_x_m, paper_y_m, paper_z_m, subpixel_x_m, subpixel_y_m, subpixel_z_m
FROM prox_cases
WHERE run = $run AND job = 'trajectory'
ORDER BY frame;
