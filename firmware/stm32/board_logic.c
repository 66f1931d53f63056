/* Pure board logic (see board_logic.h); compiled into the images and, for tests, on the host. */
#include "board_logic.h"

#include <math.h>
#include <stddef.h>

const char *reset_cause_word(uint32_t csr)
{
    if (csr & (RCC_CSR_IWDGRSTF | RCC_CSR_WWDGRSTF)) {
        return "watchdog";
    }
    if (csr & RCC_CSR_PORRSTF) {
        return "power";
    }
    if (csr & RCC_CSR_BORRSTF) {
        return "brownout";
    }
    if (csr & RCC_CSR_SFTRSTF) {
        return "software";
    }
    if (csr & RCC_CSR_LPWRRSTF) {
        return "unknown"; /* low-power management reset: not a cause the protocol names */
    }
    if (csr & RCC_CSR_PINRSTF) {
        return "pin";
    }
    return "unknown";
}

void debounce_init(debounce_t *d, bool open, uint32_t now_us)
{
    d->stable_open = open;
    d->cand_open = open;
    d->cand_since_us = now_us;
    d->cand_count = 0;
}

bool debounce_step(debounce_t *d, bool raw_open, uint32_t now_us, uint32_t need_us,
                   uint32_t need_samples)
{
    if (raw_open != d->cand_open) {
        d->cand_open = raw_open;
        d->cand_since_us = now_us;
        d->cand_count = 1;
    } else if (d->cand_count < UINT32_MAX) {
        d->cand_count++;
    }
    /* unsigned subtraction: correct across the 32-bit clock's wrap */
    if (d->cand_open != d->stable_open && d->cand_count >= need_samples &&
        (uint32_t)(now_us - d->cand_since_us) >= need_us) {
        d->stable_open = d->cand_open;
    }
    return d->stable_open;
}

uint32_t dac_code(float v, float fsv, bool *clamped)
{
    float lsb_codes = v * ((float)DAC_MID / fsv);
    bool out = !(lsb_codes >= -(float)DAC_SPAN && lsb_codes <= (float)DAC_SPAN); /* NaN too */
    if (clamped) {
        *clamped = out;
    }
    if (out) {
        return lsb_codes > 0.0f ? DAC_CODE_MAX : (lsb_codes < 0.0f ? DAC_CODE_MIN : DAC_MID);
    }
    return (uint32_t)((long)DAC_MID + lrintf(lsb_codes));
}

bool dac_code_linear(int32_t signed_code)
{
    return signed_code >= -(int32_t)DAC_SPAN && signed_code <= (int32_t)DAC_SPAN;
}

int64_t dac_linear_max_uv(int64_t fsv_uv)
{
    return fsv_uv * (int64_t)DAC_SPAN / (int64_t)DAC_MID;
}

uint32_t pll_cfgr_168mhz(uint32_t in_hz, bool hse)
{
    if (in_hz < 4000000u || in_hz > 26000000u || in_hz % 2000000u) {
        return 0;
    }
    uint32_t m = in_hz / 2000000u; /* VCO input 2 MHz */
    uint32_t n = 168u;             /* VCO 336 MHz (100..432) */
    uint32_t p = 0u;               /* /2: 168 MHz */
    uint32_t q = 7u;               /* 48 MHz, unused */
    uint32_t r = 2u;               /* /2, unused; 0 and 1 are invalid */
    return m | (n << 6) | (p << 16) | ((hse ? 1u : 0u) << 22) | (q << 24) | (r << 28);
}

uint32_t dma_stream_flag_mask(unsigned stream, unsigned *high_register)
{
    static const uint8_t shift[4] = {0u, 6u, 16u, 22u};
    if (stream > 7u) {
        return 0;
    }
    if (high_register) {
        *high_register = stream / 4u;
    }
    return 0x3Du << shift[stream % 4u]; /* FEIF, DMEIF, TEIF, HTIF, TCIF (bit 1 reserved) */
}

unsigned att_parse(const char *list, uint8_t steps_db[ATT_MAX_STEPS])
{
    unsigned count = 0;
    const char *p = list;
    if (!p || !*p) {
        return 0;
    }
    for (;;) {
        unsigned value = 0, digits = 0;
        while (*p >= '0' && *p <= '9') {
            value = value * 10u + (unsigned)(*p - '0');
            if (++digits > 3u || value > 120u) {
                return 0;
            }
            p++;
        }
        if (!digits || count == ATT_MAX_STEPS) {
            return 0;
        }
        if ((count == 0 && value != 0) || (count > 0 && value <= steps_db[count - 1])) {
            return 0;
        }
        steps_db[count++] = (uint8_t)value;
        if (*p == '\0') {
            return count;
        }
        if (*p++ != ',') {
            return 0;
        }
    }
}

uint32_t att_line_code(unsigned step, unsigned count)
{
    if (count == 0 || step >= count) {
        return 0; /* invalid: the largest attenuation */
    }
    return (count - 1u - step) & 3u;
}
