/* Converter levels: an amplitude at the amplifier input as whole DAC codes, and back.
 *
 * A channel's converter has `bits` bits over ±fsv (peak volts at the amplifier input with no
 * attenuation): 1 LSB = 2·fsv / 2^bits. Behind an attenuator of `att` dB the converter must
 * play amp · 10^(att/20); the code amplitude is that in whole LSBs (rounded half up), and the
 * amplitude actually played is code · LSB / 10^(att/20), rounded to the µV. The Python
 * emulator (masking_lab.device.emulator_levels) computes the same numbers. */
#ifndef ML_LEVEL_H
#define ML_LEVEL_H

#include <stdbool.h>
#include <stdint.h>

#define LEVEL_MAX_BITS 16
#define LEVEL_MAX_ATT_DB 60
#define LEVEL_MAX_STEPS 4

/* The output stage's linear range: the largest |code| around mid-scale it plays without
 * clipping. The reference board's DAC (STM32F4, output buffer on) is linear from 0.2 V to
 * VDDA - 0.2 V, 1798 of its 2048 codes each side of mid-scale (stm32/board_logic.h DAC_SPAN);
 * a board that does not say otherwise gets the same fraction of its converter's half range. */
#define LEVEL_REF_LINEAR_CODES 1798
#define LEVEL_REF_HALF_CODES 2048

typedef struct {
    uint8_t bits;     /* converter resolution */
    int64_t fsv_uv;   /* full scale at the amplifier input, µV peak */
} converter_t;

/* Code amplitude of amp_uv (0 <= amp_uv <= 1e9 µV) behind att_db (0..60 dB). */
int64_t level_code(const converter_t *cv, int64_t amp_uv, uint8_t att_db);

/* The amplitude a code amplitude plays at the amplifier input, µV. */
int64_t level_played_uv(const converter_t *cv, int64_t code, uint8_t att_db);

/* Largest code magnitude whose level at the amplifier input is <= limit_uv, and that the
 * converter can produce (2^(bits-1) - 1). */
int64_t level_code_limit(const converter_t *cv, int64_t limit_uv, uint8_t att_db);

/* The default linear range of a `bits`-bit converter: the reference fraction 1798/2048 of its
 * half range, rounded down (1798 for 12 bits, 28768 for 16). */
int64_t level_default_linear(uint8_t bits);

#endif
